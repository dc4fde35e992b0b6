"""A pseudo-terminal that plays a serial device, with a stable name and unplug/replug.

The emulator holds the master side; a reader opens :attr:`EmulatedPort.path` with pyserial
like a real port. The slave side is put in raw mode at creation, so bytes written before
the reader opens it are not cooked (no CR→LF, no echo). Writes never block: when nobody
reads and the kernel buffer is full, bytes are lost and counted, as on a real UART.

With a ``link`` path the port is reachable under that stable name (a symlink re-pointed on
replug, like a udev ``/dev/serial/by-id`` name); :meth:`unplug` closes both sides so the
``/dev/pts/N`` node disappears and a reader gets an I/O error, as when a USB adapter is pulled.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tty
from pathlib import Path


class EmulatedPort:
    """One emulated serial device on a pty pair."""

    def __init__(self, link: Path | None = None) -> None:
        self.link = link
        self.bytes_written = 0
        self.bytes_lost = 0  # written while nobody read and the buffer was full, or unplugged
        self._master = -1
        self._slave = -1
        self.tty_path = ""
        self.plug()

    @property
    def path(self) -> str:
        """The name a reader should open: the stable link if there is one."""
        return str(self.link) if self.link is not None else self.tty_path

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def plug(self) -> None:
        """Create the pty (again) and point the link at it."""
        if self.plugged:
            return
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.tty_path = os.ttyname(self._slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(self.tty_path)
            tmp.replace(self.link)

    def unplug(self) -> None:
        """Close the device: the tty node vanishes and readers see an I/O error."""
        if not self.plugged:
            return
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = -1

    def write(self, data: bytes) -> int:
        """Write without blocking; returns the bytes accepted, counts the rest as lost."""
        if not self.plugged:
            self.bytes_lost += len(data)
            return 0
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        self.bytes_written += n
        self.bytes_lost += len(data) - n
        return n

    def read_input(self) -> bytes:
        """Bytes the reader sent to the device (commands); drained so the reader never blocks."""
        if not self.plugged:
            return b""
        try:
            return os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        self.unplug()
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
