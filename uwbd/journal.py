"""What uwbd tells its user: Python ``logging`` to stderr, one line per event.

Every command logs through the ``uwbd`` logger. A line reads ``uwbd <command>: <message>``
(a warning says so after the colon; an error is the bare problem). Under systemd
(``JOURNAL_STREAM`` names stderr) the line starts with the syslog priority, ``<4>`` for a
warning, which journald turns into the entry's priority; systemd adds the time. On a
terminal the line starts with the local time of day. ``-q`` keeps warnings and errors,
``-v`` adds debug lines (and the traceback of an internal error).
"""

from __future__ import annotations

import logging
import os
import sys
import time

LOGGER = logging.getLogger("uwbd")
# logging level -> syslog priority, understood by journald at the start of a line
_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
             logging.CRITICAL: 2}
_LEVEL_WORD = {logging.WARNING: "warning: ", logging.DEBUG: "debug: "}


class _Formatter(logging.Formatter):
    def __init__(self, command: str, journal: bool, clock: bool) -> None:
        super().__init__()
        self.command = command
        self.journal = journal
        self.clock = clock

    def format(self, record: logging.LogRecord) -> str:
        head = f"<{_PRIORITY.get(record.levelno, 6)}>" if self.journal else ""
        if self.clock:
            stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
            head += f"{stamp}.{int(record.msecs):03d} "
        text = record.getMessage()
        if record.exc_info and LOGGER.isEnabledFor(logging.DEBUG):
            text += "\n" + self.formatException(record.exc_info)
        first, *more = text.splitlines() or [""]
        line = f"{head}uwbd {self.command}: {_LEVEL_WORD.get(record.levelno, '')}{first}"
        # each line its own journal entry: each gets the priority and the command
        return "\n".join([line, *(f"{head}uwbd {self.command}:   {m}" for m in more)])


def setup(command: str, verbosity: int = 0) -> logging.Logger:
    """Route the ``uwbd`` logger to stderr for ``command``: ``verbosity`` -1 (``-q``),
    0 or 1 (``-v``)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(command, journal=_to_journal(), clock=sys.stderr.isatty()))
    for old in list(LOGGER.handlers):
        LOGGER.removeHandler(old)
    LOGGER.addHandler(handler)
    LOGGER.setLevel(logging.WARNING if verbosity < 0 else
                    logging.DEBUG if verbosity > 0 else logging.INFO)
    LOGGER.propagate = False
    return LOGGER


def _to_journal() -> bool:
    """stderr is the journal stream systemd gave us (``JOURNAL_STREAM`` is its device:inode)."""
    device, _, inode = os.environ.get("JOURNAL_STREAM", "").partition(":")
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError):
        return False
    return f"{st.st_dev}:{st.st_ino}" == f"{device}:{inode}"


def get(name: str) -> logging.Logger:
    """The logger of one part of uwbd (``uwbd.daemon``, ``uwbd.log`` ...)."""
    return LOGGER.getChild(name)
