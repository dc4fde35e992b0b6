"""The documentation holds: the configuration reference and the template are generated from
the schema and current; the template is a config ``check-config`` accepts, at the defaults;
the README is short and every link resolves; and every shell block in the README and the
guides runs as written, or names what runs it, or says why it cannot run here."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from uwbd.config import parse, reference
from uwbd.config.model import LOG_DIRECTORY, ROTATE_MB, ROTATE_MINUTES
from uwbd.config.schema import TABLES
from uwbd.config.zenoh_session import ZENOH_PATHS, session_config

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHARED = ROOT.parent / "shared"
# a block runs unless the line before it names what runs it, or why it cannot run here
MARKER = re.compile(r"<!-- (?:walkthrough|run by): (\S+)|<!-- not run here: .+ -->")


def test_the_configuration_reference_and_the_template_are_current() -> None:
    assert reference.DOC.read_text(encoding="utf-8") == reference.markdown(), \
        "docs/configuration.md is stale: python -m uwbd.config.reference"
    assert reference.TEMPLATE.read_text(encoding="utf-8") == reference.template(), \
        "config/template.toml is stale: python -m uwbd.config.reference"


def test_every_key_of_the_schema_has_its_meaning_and_default() -> None:
    assert set(reference.REFERENCE) == set(TABLES)
    for section, keys in TABLES.items():
        assert set(reference.REFERENCE[section]) == set(keys), section
        for name, entry in reference.REFERENCE[section].items():
            assert entry.meaning and (entry.default is not None or entry.unset), (section, name)
            if entry.default is not None:  # the default is a value the key accepts
                assert keys[name].problem(entry.default) is None, (section, name)


def test_the_template_passes_check_config_and_holds_the_defaults() -> None:
    checked = subprocess.run([sys.executable, "-m", "uwbd", "check-config",
                              str(reference.TEMPLATE)], capture_output=True, text=True,
                             timeout=60, check=False)
    assert checked.returncode == 0 and "warning" not in checked.stderr.lower(), checked.stderr
    text = reference.TEMPLATE.read_text(encoding="utf-8")
    bare = text.split("\n[robot]")[0]  # the sources and anchors only: every key at default
    full, defaults = parse(text), parse(bare)
    assert full.filter_config() == defaults.filter_config()
    for prop in ("pose_period_ns", "status_period_ns", "aligner_wait_ns", "zenoh_prefix",
                 "nav_frame_id", "body_frame_id", "ros2_settings"):
        assert getattr(full, prop) == getattr(defaults, prop), prop
    assert full.range_model_settings() == defaults.range_model_settings()
    for key in ("listen", "connect", "mode", "multicast_scouting"):  # the same Zenoh session
        where = ZENOH_PATHS[key]
        assert session_config(full.zenoh).get_json(where) == \
            session_config(defaults.zenoh).get_json(where), key
    assert full.log == {"directory": LOG_DIRECTORY, "rotate_mb": ROTATE_MB,  # as run reads them
                        "rotate_minutes": ROTATE_MINUTES}


def test_the_readme_is_short_and_every_link_resolves() -> None:
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 150
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            if target.startswith(("http://", "https://")):
                continue
            path = (page.parent / target.split("#")[0]).resolve()
            assert path.exists(), f"{page.name}: a link to {target}, which is not there"


def _blocks() -> list[tuple[str, int, str, str]]:
    """(page, line, the marker before it or "", the block) of every ```sh block."""
    found = []
    for page in PAGES:
        lines = page.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            if line.strip() == "```sh":
                end = next(j for j in range(i + 1, len(lines)) if lines[j].strip() == "```")
                before = lines[i - 1].strip() if i else ""
                indent = len(line) - len(line.lstrip())
                found.append((page.name, i + 1, before,
                              "\n".join(x[indent:] for x in lines[i + 1:end])))
    return found


BLOCKS = _blocks()


def test_every_marked_block_names_what_runs_it() -> None:
    first = next(b for b in BLOCKS if b[0] == "README.md")
    assert ".ci/run" in first[2] or "pip install" in first[3]  # the install: .ci/run's
    for page, line, before, _ in BLOCKS:
        match = MARKER.search(before)
        if match and match.group(1):
            assert (ROOT / match.group(1)).exists(), f"{page}:{line}: {match.group(1)}"


@pytest.mark.parametrize("page, line, before, block",
                         [b for b in BLOCKS if not MARKER.search(b[2])
                          and "pip install" not in b[3]],
                         ids=lambda v: str(v) if isinstance(v, (str, int)) else None)
def test_every_guide_block_runs_as_written(tmp_path: Path, page: str, line: int, before: str,
                                            block: str) -> None:
    """Run in a folder that sees the repository's config/ and docs/ and the shared data at
    ../shared, as from the repository root; ``uwbd`` is the installed one."""
    if "../shared/data" in block and not SHARED.exists():
        pytest.skip("../shared/data is not here")
    work = tmp_path / "repo"
    work.mkdir()
    for name in ("config", "docs"):
        (work / name).symlink_to(ROOT / name)
    if SHARED.exists():
        (tmp_path / "shared").symlink_to(SHARED)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=work, env=env,
                          capture_output=True, text=True, timeout=240, check=False)
    assert done.returncode == 0, f"{page}:{line}\n{block}\n{done.stderr[-2000:]}"
    assert "Traceback" not in done.stderr
