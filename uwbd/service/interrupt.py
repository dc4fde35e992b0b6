"""Waiting in the foreground until work ends or the user (or systemd) says stop, and a
reader of stdout that goes away (``| head``)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from types import FrameType


def wait_until(done: threading.Event, poll_s: float = 0.2) -> None:
    """Block until ``done`` is set, Ctrl-C or SIGTERM; both signals end the wait quietly.

    Once a stop was asked for, further SIGINT/SIGTERM are ignored for the rest of the
    process, so a second Ctrl-C (or a supervisor that signals the process and then its
    group, as GNU ``timeout`` does) cannot cut the clean-up short; every wait in the
    clean-up is bounded, so it cannot hang either.
    """
    def on_term(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        while not done.wait(poll_s):
            pass
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        return
    signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """Finish cleaning up even when Ctrl-C comes again, or a supervisor signals the process
    and its group (GNU ``timeout`` does both): further SIGINT/SIGTERM are ignored inside."""
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def quiet_stdout() -> None:
    """stdout's reader went away (``| head``): send what is left to /dev/null, so the
    interpreter's last flush does not complain."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
