"""The robot's install: the daemon needs none of the tools extra (matplotlib, scipy,
filterpy), and a command that does says how to get it."""

from __future__ import annotations

import os
from pathlib import Path

from procs import one_line, uwbd

TOOLS_EXTRA = ("matplotlib", "scipy", "filterpy")
BLOCKER = f'''
import importlib.abc, sys

class NotInstalled(importlib.abc.MetaPathFinder):
    """As on a robot installed without the tools extra."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {TOOLS_EXTRA!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, NotInstalled())
'''


def test_the_daemon_and_its_log_tools_run_without_the_tools_extra(tmp_path: Path) -> None:
    (tmp_path / "sitecustomize.py").write_text(BLOCKER)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    demo = uwbd("demo", "--duration", "3", env=env, cwd=tmp_path)
    assert demo.returncode == 0 and "Traceback" not in demo.stderr, demo.stderr
    assert "pose (" in demo.stdout
    sim = uwbd("simulate", "-o", "s.mcap", "--duration", "25", "--seed", "1", env=env,
               cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    replay = uwbd("replay", "s.mcap", env=env, cwd=tmp_path)
    assert replay.returncode == 0 and "poses" in replay.stdout, replay.stderr
    check = uwbd("check-config", str(Path(__file__).parents[1] / "config" / "demo.toml"),
                 env=env)
    assert check.returncode == 0, check.stderr
    # the one command that needs the extra says so, in one line
    one_line(uwbd("report", "s.mcap", env=env, cwd=tmp_path), 2,
             "report needs the tools extra", "pip install 'uwbd[tools]'")
