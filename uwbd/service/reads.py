"""Who reads the ports: with the C extension built (``uwbd.service._reader``, as the C core,
unless ``UWBD_PURE_PYTHON=1``), a thread of its own, which wakes the event loop only when a
read may change what subscribers see (:class:`ThreadReads`); else the event loop itself,
one callback per read (:class:`LoopReads`). Either hands the same reads, with the same
times, in the same order, to :class:`~uwbd.service.ports.ReadQueue`.
"""

from __future__ import annotations

import asyncio
import os
from types import ModuleType

from uwbd.fusion.core import native
from uwbd.service.ports import (
    IMU_ONLY_DRIVERS,
    MAX_QUEUE_NS,
    EpochClock,
    ReadQueue,
    SerialSource,
)


class LoopReads:
    """The ports in the event loop (``add_reader``): a callback for every read."""

    name = "event loop"
    dropped_bytes = 0

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop

    def watch(self, source: SerialSource) -> None:
        self.loop.add_reader(source.fd, source.readable)

    def unwatch(self, source: SerialSource) -> None:
        self.loop.remove_reader(source.fd)

    def drain(self) -> None:
        """Every read went in as it came."""

    def close(self) -> None:
        """Nothing of its own to stop."""


class ThreadReads:
    """The ports read by the C reader's thread (``_reader.c``), which wakes the event loop
    for a read from a UWB source, one at or after the next pose's time, a lost port, or
    reads held ``MAX_QUEUE_NS``: ~60 wakeups a second instead of ~210 with a 200 Hz IMU."""

    name = "reader thread"

    def __init__(self, loop: asyncio.AbstractEventLoop, clock: EpochClock, queue: ReadQueue,
                 module: ModuleType) -> None:
        self.loop = loop
        self.queue = queue
        self._reader = module.Reader(clock.offset_ns, MAX_QUEUE_NS)
        # each watch of a port gets a token: a loss the thread held for a port that has
        # been released since (and perhaps reopened) is not the new port's
        self._tokens: dict[int, SerialSource] = {}
        self._retired: list[int] = []  # unwatched: forgotten after the next drain
        self._next_token = 0
        self._wake_fd = self._reader.wake_fd
        loop.add_reader(self._wake_fd, self.drain)

    @property
    def dropped_bytes(self) -> int:
        return int(self._reader.dropped_bytes)

    def watch(self, source: SerialSource) -> None:
        token = self._next_token
        self._next_token += 1
        self._reader.add(source.fd, token, source.cfg.driver not in IMU_ONLY_DRIVERS)
        self._tokens[token] = source
        source.token = token

    def unwatch(self, source: SerialSource) -> None:
        self._reader.remove(source.fd)  # not read again once this returns
        self._retired.append(source.token)
        # a loss the thread saw before this is no longer news: the port is released already
        # (by a failed write, say, at the same unplug), its retry under way
        source.token = -1

    def drain(self) -> None:
        """The held reads into the queue, in order; lost ports to their source."""
        retired, self._retired = self._retired, []
        tokens, held = self._tokens, []
        lost = []
        for token, t_ns, data, error in self._reader.drain():
            if data is not None:  # read before any loss: real data
                held.append(tokens[token].counted(t_ns, data))
            elif token == tokens[token].token:
                lost.append((tokens[token], error))
        if held:  # they waited in the thread until one mattered: all go on now
            self.queue.push_held(held)
        for source, error in lost:  # (the thread holds a port's loss after its reads)
            source.lost(OSError(error, os.strerror(error)) if error
                        else OSError("port closed (device gone)"))
        for token in retired:  # every read of theirs was held before the drain above
            del tokens[token]
        self._reader.set_due(self.queue.pipeline.next_pose_due_ns)

    def close(self) -> None:
        self.loop.remove_reader(self._wake_fd)
        self._reader.close()


def _reader_module() -> ModuleType | None:
    """The C reader, when built and not ruled out by ``UWBD_PURE_PYTHON``."""
    if native.core is None:  # the same switch as the C core's (and built with it)
        return None
    try:
        from uwbd.service import _reader  # noqa: PLC0415
    except ImportError:
        return None
    return _reader


def make_reads(loop: asyncio.AbstractEventLoop, clock: EpochClock,
               queue: ReadQueue) -> LoopReads | ThreadReads:
    module = _reader_module()
    return LoopReads(loop) if module is None else ThreadReads(loop, clock, queue, module)
