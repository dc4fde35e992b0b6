"""Subprocess helpers for tests that run the real CLI: nothing here can hang on a process
that died or went quiet."""

from __future__ import annotations

import os
import selectors
import subprocess
import sys
import time
from pathlib import Path

UWBD = [sys.executable, "-m", "uwbd"]
UNBUFFERED = {**os.environ, "PYTHONUNBUFFERED": "1"}


def uwbd(*args: str, cwd: Path | None = None, timeout: float = 120,
         env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*UWBD, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, check=False, env=env)


def read_until(proc: subprocess.Popen[bytes], marker: bytes, timeout_s: float,
               stream: str = "stdout") -> bytes:
    """What ``proc`` wrote on ``stream`` up to and including the line holding ``marker``;
    fails when the process ends or ``timeout_s`` passes first."""
    pipe = getattr(proc, stream)
    assert pipe is not None
    seen = b""
    deadline = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(pipe, selectors.EVENT_READ)
        while marker not in seen:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no {marker!r} in {timeout_s} s; got {seen[-2000:]!r}")
            if sel.select(left):
                chunk = os.read(pipe.fileno(), 65536)
                if not chunk:
                    raise AssertionError(f"{stream} ended (rc {proc.poll()}) before {marker!r}; "
                                         f"got {seen[-2000:]!r}")
                seen += chunk
    return seen


def one_line(result: subprocess.CompletedProcess[str], code: int, *needles: str) -> str:
    """The command failed with ``code`` and said so in exactly one line holding ``needles``."""
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert result.returncode == code, (result.returncode, result.stderr)
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]
