"""The daemon's serial ports: opened, read, stamped, held until they matter, reopened.

Each source is a serial port read without blocking: pyserial opens it (non-blocking, with an
exclusive lock) and every read is stamped as it completes with :class:`EpochClock`:
Unix-epoch nanoseconds that advance with the monotonic clock, so an NTP step (a robot
without a real-time clock, just after boot) cannot make the aligner drop frames as late or
the filter see a leap. A port that is absent at start or vanishes (unplugged) is retried
with a backoff of 0.1 s doubling to 2 s; its state shows in the status and every change of
it in a log line.

Who reads the ports (a thread, or the event loop) is :mod:`uwbd.service.reads`'s; either
hands the same reads, with the same times, in the same order, to :class:`ReadQueue`.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import serial

from drivers.dwm1001_tlv import LOC_GET_REQUEST
from uwbd import journal
from uwbd.config import SourceConfig
from uwbd.service.pipeline import Pipeline
from uwbd.service.sample_times import BATCHED_DRIVERS

READ_BYTES = 4096  # as _reader.c's
# drivers whose device speaks only when asked: (request bytes, period s)
POLLED = {"dwm1001-tlv": (LOC_GET_REQUEST, 0.1)}
BACKOFF_START_S = 0.1
BACKOFF_MAX_S = 2.0
STABLE_OPEN_S = 5.0  # open this long before a loss: the backoff starts again from the start
IMU_ONLY_DRIVERS = BATCHED_DRIVERS  # their reads may wait for the next pose (ReadQueue)
MAX_QUEUE_NS = 100_000_000
# Batched reads (IMU-only ports): the port's VMIN is set so that a read returns about once
# per pose period: BATCH_SHARE of the bytes a period brings, at the byte rate measured over
# BATCH_LEARN_NS; VMIN 0 again (a read for every byte) once no read has come for
# TAIL_AFTER_PERIODS periods, so that what a device sent last is not held below VMIN
BATCH_LEARN_NS = 1_000_000_000
BATCH_SHARE = 0.8
TAIL_AFTER_PERIODS = 3
MAX_VMIN = 255  # termios' c_cc is one byte
LOG = journal.get("daemon")


class Reads(Protocol):
    """Who reads the ports (:mod:`uwbd.service.reads`): a port is watched once open."""

    def watch(self, source: SerialSource) -> None: ...

    def unwatch(self, source: SerialSource) -> None: ...


@dataclass
class SourceState:
    state: str = "closed"  # closed | open | stalled (open, but no byte for stall_after_s)
    opens: int = 0
    losses: int = 0
    last_error: str = ""
    bytes_read: int = 0
    last_read_ns: int | None = None  # when the last read returned (EpochClock)
    stalls: int = 0
    read_batch_bytes: int = 0  # the port's VMIN: a read waits for this many bytes (0: any)


class EpochClock:
    """``time.time_ns()`` read once, then advanced by ``time.monotonic_ns()``."""

    def __init__(self) -> None:
        self.offset_ns = time.time_ns() - time.monotonic_ns()

    def now_ns(self) -> int:
        return self.offset_ns + time.monotonic_ns()


class ReadQueue:
    """Reads wait here until they matter, then go to the pipeline a few at a time, in order.

    A process woken from sleep runs on cold caches: a read costs about three times the CPU
    after a 5 ms pause that it costs in a tight loop (measured), so handing 200 IMU reads a
    second to the pipeline one by one was most of the daemon's CPU. A read goes on at once,
    with all those that waited before it, when it can change what subscribers see: it comes
    from a UWB source (an epoch: an update and a pose), or it is at or past the time the
    next pose is due. Otherwise it waits, at most ``MAX_QUEUE_NS`` of read time. Sources,
    times and order are unchanged, so a replay of the log still matches bit for bit, and no
    pose leaves later than it would have. Reads that wait are the time to do work that
    can wait too, ``idle`` (writing the log).
    """

    def __init__(self, pipeline: Pipeline, idle: Callable[[], None] = lambda: None) -> None:
        self.pipeline = pipeline
        self.idle = idle  # called on reads that wait: time for work that delays no pose
        self.urgent = {s.name for s in pipeline.config.sources
                       if s.driver not in IMU_ONLY_DRIVERS}
        self._pending: list[tuple[str, int, bytes]] = []
        self.failure: Exception | None = None  # what the pipeline raised; reads then stop

    def push(self, source: str, t_ns: int, data: bytes) -> None:
        pending = self._pending
        pending.append((source, t_ns, data))
        if (source in self.urgent or t_ns >= self.pipeline.next_pose_due_ns
                or t_ns - pending[0][1] >= MAX_QUEUE_NS):
            self.flush()
        else:
            try:
                self.idle()
            except Exception as err:  # the log's own work: reported like a sink's
                self.pipeline.sink_failed(self.idle, err)

    def push_held(self, reads: list[tuple[str, int, bytes]]) -> None:
        """Reads the reader thread held until one of them mattered: all go on at once,
        then the work that can wait (``idle``) has its turn, after the pose."""
        self._pending += reads
        self.flush()
        try:
            self.idle()
        except Exception as err:
            self.pipeline.sink_failed(self.idle, err)

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        if self.failure is not None:
            return
        on_bytes = self.pipeline.on_bytes
        try:
            for source, t_ns, data in pending:
                on_bytes(source, t_ns, data)
        except Exception as err:
            self.fail(err, f"on a read of {source}")

    def fail(self, err: Exception, doing: str) -> None:
        """The pipeline raised (a bug: bad input is counted, never raised): reads stop."""
        self.failure = err
        LOG.error("the pipeline failed %s: %s: %s; stopping (please report this with the log)",
                  doing, type(err).__name__, err, exc_info=True)


def batch_vmin(rate_bps: float, pose_period_ns: int) -> int:
    """A batched port's VMIN at a byte rate: ``BATCH_SHARE`` of a pose period's bytes, at
    most ``MAX_VMIN``; 0 under 2 (1 is what 0 already does: a read for any byte)."""
    vmin = min(MAX_VMIN, int(rate_bps * pose_period_ns / 1e9 * BATCH_SHARE))
    return vmin if vmin >= 2 else 0


class SerialSource:
    """One port: opened, handed to ``reads`` (:func:`make_reads`), reopened when lost."""

    def __init__(self, cfg: SourceConfig, queue: ReadQueue,
                 loop: asyncio.AbstractEventLoop, clock: EpochClock,
                 reads: Reads) -> None:
        self.cfg = cfg
        self.clock = clock
        self.queue = queue
        self.loop = loop
        self.reads = reads
        self.info = SourceState()
        self.token = -1  # ThreadReads': which watch of the port this is
        self._port: serial.Serial | None = None
        self.fd = -1
        self._backoff_s = BACKOFF_START_S
        self._opened_at = 0.0
        self._opened_ns = 0
        self._retry: asyncio.TimerHandle | None = None
        self._poller: asyncio.TimerHandle | None = None
        self._closed = False
        self._rate_mark: tuple[int, int] | None = None  # (t_ns, bytes read) to measure from

    def start(self) -> None:
        self._open()

    def _open(self) -> None:
        self._retry = None
        if self._closed:
            return
        try:
            port = serial.Serial(self.cfg.port, self.cfg.baud, timeout=0, exclusive=True)
        except (OSError, ValueError) as err:
            self._schedule_retry(f"cannot open {self.cfg.port}: {reason(err)}")
            return
        self._port, self.fd = port, port.fileno()
        try:
            self.reads.watch(self)
        except OSError as err:  # the reader cannot take it (more ports than it has room for)
            with contextlib.suppress(OSError):
                port.close()
            self._port, self.fd = None, -1
            self._schedule_retry(f"cannot read {self.cfg.port}: {reason(err)}")
            return
        self.info.state = "open"
        self.info.opens += 1
        self._opened_ns = self.clock.now_ns()
        LOG.info("%s: %s %s at %d baud (%s)", self.cfg.name,
                 "opened" if self.info.opens == 1 else "reopened", self.cfg.port,
                 self.cfg.baud, self.cfg.driver)
        self._opened_at = self.loop.time()
        if self.cfg.driver in POLLED:
            self._poll()

    def _poll(self) -> None:
        """Request devices that only answer requests (DWM1001 TLV ``loc_get``) at 10 Hz."""
        request, period_s = POLLED[self.cfg.driver]
        if self._port is None or self._closed:
            return
        try:
            os.write(self.fd, request)
        except BlockingIOError:
            pass  # output buffer full: the next period asks again
        except OSError as err:
            self.lost(err)
            return
        self._poller = self.loop.call_later(period_s, self._poll)

    def _schedule_retry(self, reason: str) -> None:
        if reason != self.info.last_error or self.info.state != "closed":
            LOG.warning("%s: %s; retrying every %.1f s at most", self.cfg.name, reason,
                        BACKOFF_MAX_S)
        self.info.state = "closed"
        self.info.last_error = reason
        self._retry = self.loop.call_later(self._backoff_s, self._open)
        self._backoff_s = min(self._backoff_s * 2, BACKOFF_MAX_S)

    def readable(self) -> None:
        """The event loop's callback (:class:`LoopReads`): one read, stamped as it returns."""
        try:
            data = os.read(self.fd, READ_BYTES)
            if not data:
                raise OSError("port closed (device gone)")
        except BlockingIOError:
            return
        except OSError as err:
            self.lost(err)
            return
        # a terminal whose VMIN is set (batch_reads) gives at most 64 bytes a read (the
        # kernel's chunk): what else is there now is read too, as one read (as _reader.c)
        while 0 < len(data) < READ_BYTES:
            try:
                more = os.read(self.fd, READ_BYTES - len(data))
            except OSError:  # nothing more (or a loss: the next callback says so)
                break
            if not more:
                break
            data += more
        self.take(self.clock.now_ns(), data)

    def take(self, t_ns: int, data: bytes) -> None:
        """A read of ``data`` that returned at ``t_ns``."""
        self.info.bytes_read += len(data)
        self.info.last_read_ns = t_ns
        self.queue.push(self.cfg.name, t_ns, data)

    def counted(self, t_ns: int, data: bytes) -> tuple[str, int, bytes]:
        """A read the reader thread held, counted; for :meth:`ReadQueue.push_held`."""
        self.info.bytes_read += len(data)
        self.info.last_read_ns = t_ns
        return self.cfg.name, t_ns, data

    def check_stall(self, now_ns: int, stall_after_ns: int) -> None:
        """An open port that has not given a byte for ``stall_after_ns`` (since it opened,
        or since its last read) is ``stalled`` — the device off or hung, a cable half out —
        and said once; a read makes it ``open`` again, and that is said too."""
        if self.info.state == "closed":
            return
        last = self.info.last_read_ns
        since = self._opened_ns if last is None or last < self._opened_ns else last
        quiet_ns = now_ns - since
        if self.info.state == "open" and quiet_ns > stall_after_ns:
            self.info.state = "stalled"
            self.info.stalls += 1
            LOG.warning("%s: no byte from %s for %.1f s: stalled (is the device powered and "
                        "sending? is the baud %d right?)", self.cfg.name, self.cfg.port,
                        quiet_ns / 1e9, self.cfg.baud)
        elif self.info.state == "stalled" and quiet_ns <= stall_after_ns:
            self.info.state = "open"
            LOG.info("%s: bytes again from %s", self.cfg.name, self.cfg.port)

    def batch_reads(self, now_ns: int, pose_period_ns: int) -> None:
        """An IMU-only port, open and sending: its VMIN set from the measured byte rate so
        that a read returns about once per pose period (a few samples a read, spread by
        the pipeline over the learned sample period) instead of once per sample; back to
        0 once the device has gone quiet for a few periods (the tail below VMIN is read).
        Called on the daemon's tick; a port that takes no termios (not a tty) is left be."""
        info = self.info
        if self.cfg.driver not in IMU_ONLY_DRIVERS or self.fd < 0 or info.state != "open":
            self._rate_mark = None
            return
        last = info.last_read_ns
        if info.read_batch_bytes and (
                last is None or now_ns - last > TAIL_AFTER_PERIODS * pose_period_ns):
            self._set_vmin(0)
            self._rate_mark = None
            return
        mark = self._rate_mark
        if mark is None or now_ns <= mark[0]:
            self._rate_mark = (now_ns, info.bytes_read)
            return
        if now_ns - mark[0] < BATCH_LEARN_NS:
            return
        rate_bps = (info.bytes_read - mark[1]) * 1e9 / (now_ns - mark[0])
        self._rate_mark = (now_ns, info.bytes_read)
        vmin = batch_vmin(rate_bps, pose_period_ns)
        old = info.read_batch_bytes
        if abs(vmin - old) > 0.1 * max(vmin, old):  # (the rate's jitter changes nothing)
            self._set_vmin(vmin)

    def _set_vmin(self, vmin: int) -> None:
        try:
            attrs = termios.tcgetattr(self.fd)
            attrs[6][termios.VMIN] = vmin
            attrs[6][termios.VTIME] = 0
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except (termios.error, OSError):
            return  # not a terminal (or gone: the read says so): reads stay as they are
        self.info.read_batch_bytes = vmin

    def lost(self, err: OSError) -> None:
        self.info.losses += 1
        if self.loop.time() - self._opened_at >= STABLE_OPEN_S:
            self._backoff_s = BACKOFF_START_S  # it worked a while: retry quickly
        # else a port that opens and fails at once keeps backing off (no flood of lines)
        self._release()
        self._schedule_retry(f"lost {self.cfg.port}: {reason(err)}")

    def _release(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            self._poller = None
        if self._port is not None:
            self.reads.unwatch(self)
            with contextlib.suppress(OSError):  # the device is gone: nothing left to release
                self._port.close()
            self._port, self.fd = None, -1
        self.info.read_batch_bytes = 0  # a port opened again starts with a read per byte
        self._rate_mark = None

    def close(self) -> None:
        self._closed = True
        if self._retry is not None:
            self._retry.cancel()
        self._release()


def reason(err: Exception) -> str:
    """An OS error as a person reads it, with what to check: ``No such file or directory (is
    it plugged in? ...)`` rather than pyserial's ``could not open port ...: [Errno 2] ...``."""
    code = getattr(err, "errno", None)
    if not isinstance(code, int):
        return str(err)
    hint = {errno.ENOENT: " (is it plugged in? see ls /dev/serial/by-id/)",
            errno.EACCES: " (is the user in group dialout?)",
            errno.EBUSY: " (another program has it open)",
            errno.EAGAIN: " (another program has it locked)"}.get(code, "")
    return os.strerror(code) + hint

