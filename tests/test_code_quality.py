"""ruff and mypy stay clean: run them as the developers do."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ruff_is_clean() -> None:
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=ROOT,
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_is_clean() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True,
                            text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


MAX_MODULE_LINES = 450


def test_no_module_is_over_450_lines() -> None:
    """A module does one job: past this many lines it is doing two (split it)."""
    long = [f"{p.relative_to(ROOT)}: {n}" for p in sorted(ROOT.glob("uwbd/**/*.py"))
            + sorted(ROOT.glob("drivers/**/*.py"))
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not long, "modules over 450 lines: " + ", ".join(long)
