"""systemd notifications (``sd_notify``): READY, WATCHDOG, STATUS, STOPPING.

A few lines of our own instead of the ``sdnotify`` package, which drops non-Latin-1 status
text silently and never closes its socket. Without ``NOTIFY_SOCKET`` (not under systemd)
every call does nothing. ``@name`` addresses are abstract sockets.
"""

from __future__ import annotations

import contextlib
import os
import socket


class Notifier:
    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        usec = os.environ.get("WATCHDOG_USEC", "")
        self.watchdog_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else None
        self._sock: socket.socket | None = None
        if self.address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)

    def notify(self, *assignments: str) -> None:
        """Send ``KEY=value`` lines in one datagram; errors are ignored (best effort)."""
        if self._sock is None:
            return
        with contextlib.suppress(OSError):  # systemd gone: notifications are advisory
            self._sock.sendto("\n".join(assignments).encode(), self.address)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
