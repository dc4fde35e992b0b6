"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

# the same examples on every run (a run on CI fails or passes as it did here); a search
# for new ones: HYPOTHESIS_PROFILE=explore
settings.register_profile("fixed", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fixed"))


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A folder on a 256 kB tmpfs, to fill (root and mount, else the test is skipped)."""
    folder = tmp_path / "small"
    folder.mkdir()
    if os.geteuid() != 0 or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)],
            capture_output=True, check=False).returncode != 0:
        pytest.skip("needs a small tmpfs (root and mount)")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)
