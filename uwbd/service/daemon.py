"""``uwbd run``: serial ports → pipeline → MCAP (and, with the Zenoh sink, the network).

Each source is a serial port read without blocking: pyserial opens it (non-blocking, with an
exclusive lock), its file descriptor goes into the event loop with ``add_reader``, and every
read is stamped as it completes with :class:`EpochClock`: Unix-epoch nanoseconds that
advance with the monotonic clock, so an NTP step (a robot without a real-time clock, just
after boot) cannot make the aligner drop frames as late or the filter see a leap. A port
that is absent at start or vanishes (unplugged) is retried with a backoff of 0.1 s doubling
to 2 s; its state shows in the status and every change of it in a log line. SIGINT and
SIGTERM stop the loop and finish the log.

The status is published on the wall clock, whether or not data arrives. The systemd
watchdog is fed by the loop's tick, so a hung loop is restarted; an exception out of the
pipeline (a bug: bad input is counted, never raised) is logged, the log finished, and the
run ends with :class:`PipelineError` (exit code 1, so systemd restarts it).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import serial
import zenoh

from drivers.dwm1001_tlv import LOC_GET_REQUEST
from uwbd import __version__, journal
from uwbd.config import Config, SourceConfig
from uwbd.fusion import native
from uwbd.logs.sink import McapSink
from uwbd.service.narrator import Narrator
from uwbd.service.notify import Notifier
from uwbd.service.pipeline import Pipeline, Sink
from uwbd.service.zenohsink import ZenohSink, zenoh_reason

READ_BYTES = 4096
# drivers whose device speaks only when asked: (request bytes, period s)
POLLED = {"dwm1001-tlv": (LOC_GET_REQUEST, 0.1)}
BACKOFF_START_S = 0.1
BACKOFF_MAX_S = 2.0
STABLE_OPEN_S = 5.0  # open this long before a loss: the backoff starts again from the start
IMU_ONLY_DRIVERS = {"wit"}  # their reads may wait for the next pose (ReadQueue)
MAX_QUEUE_NS = 100_000_000
ZENOH_RETRY_S = 5.0
LOG = journal.get("daemon")


class PipelineError(RuntimeError):
    """The pipeline raised: the run stopped (its log is finished)."""


@dataclass
class SourceState:
    state: str = "closed"  # closed | open
    opens: int = 0
    losses: int = 0
    last_error: str = ""
    bytes_read: int = 0


class EpochClock:
    """``time.time_ns()`` read once, then advanced by ``time.monotonic_ns()``."""

    def __init__(self) -> None:
        self._offset_ns = time.time_ns() - time.monotonic_ns()

    def now_ns(self) -> int:
        return self._offset_ns + time.monotonic_ns()


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


class SerialSource:
    def __init__(self, cfg: SourceConfig, queue: ReadQueue,
                 loop: asyncio.AbstractEventLoop, clock: EpochClock) -> None:
        self.cfg = cfg
        self.clock = clock
        self.queue = queue
        self.loop = loop
        self.info = SourceState()
        self._port: serial.Serial | None = None
        self._fd = -1
        self._backoff_s = BACKOFF_START_S
        self._opened_at = 0.0
        self._retry: asyncio.TimerHandle | None = None
        self._poller: asyncio.TimerHandle | None = None
        self._closed = False

    def start(self) -> None:
        self._open()

    def _open(self) -> None:
        self._retry = None
        if self._closed:
            return
        try:
            port = serial.Serial(self.cfg.port, self.cfg.baud, timeout=0, exclusive=True)
        except (OSError, ValueError) as err:
            self._schedule_retry(f"cannot open {self.cfg.port}: {_reason(err)}")
            return
        self._port, self._fd = port, port.fileno()
        self.loop.add_reader(self._fd, self._readable)
        self.info.state = "open"
        self.info.opens += 1
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
            os.write(self._fd, request)
        except BlockingIOError:
            pass  # output buffer full: the next period asks again
        except OSError as err:
            self._lost(err)
            return
        self._poller = self.loop.call_later(period_s, self._poll)

    def _schedule_retry(self, reason: str) -> None:
        if reason != self.info.last_error or self.info.state == "open":
            LOG.warning("%s: %s; retrying every %.1f s at most", self.cfg.name, reason,
                        BACKOFF_MAX_S)
        self.info.state = "closed"
        self.info.last_error = reason
        self._retry = self.loop.call_later(self._backoff_s, self._open)
        self._backoff_s = min(self._backoff_s * 2, BACKOFF_MAX_S)

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, READ_BYTES)
            if not data:
                raise OSError("port closed (device gone)")
        except BlockingIOError:
            return
        except OSError as err:
            self._lost(err)
            return
        t_ns = self.clock.now_ns()
        self.info.bytes_read += len(data)
        self.queue.push(self.cfg.name, t_ns, data)

    def _lost(self, err: OSError) -> None:
        self.info.losses += 1
        if self.loop.time() - self._opened_at >= STABLE_OPEN_S:
            self._backoff_s = BACKOFF_START_S  # it worked a while: retry quickly
        # else a port that opens and fails at once keeps backing off (no flood of lines)
        self._release()
        self._schedule_retry(f"lost {self.cfg.port}: {_reason(err)}")

    def _release(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            self._poller = None
        if self._port is not None:
            self.loop.remove_reader(self._fd)
            with contextlib.suppress(OSError):  # the device is gone: nothing left to release
                self._port.close()
            self._port, self._fd = None, -1

    def close(self) -> None:
        self._closed = True
        if self._retry is not None:
            self._retry.cancel()
        self._release()


async def run(config: Config, log_dir: Path, duration_s: float | None = None,
              extra_sinks: tuple[Sink, ...] = (),
              on_log: Callable[[McapSink], None] | None = None,
              summary_s: float = 60.0, where: str = "") -> Pipeline:
    """Run until SIGINT/SIGTERM (or ``duration_s``); returns the finished pipeline.
    ``on_log`` is handed the log sink first, for callers with more to log (the demo: truth).
    ``summary_s``: how often a health line is logged; ``where``: the config's file name.
    Raises :class:`PipelineError` (after finishing the log) if the pipeline raised."""
    loop = asyncio.get_running_loop()
    rotate_mb = config.log.get("rotate_mb", 256)
    rotate_min = config.log.get("rotate_minutes", 60)
    mcap = McapSink(config, directory=log_dir, rotate_bytes=int(rotate_mb * 1e6),
                    rotate_ns=int(rotate_min * 60e9), paced=True)
    if on_log is not None:
        on_log(mcap)
    sources: list[SerialSource] = []
    narrator = Narrator(summary_s, ports=lambda: ", ".join(
        f"{s.cfg.name} {s.info.state}" for s in sources))
    sinks: list[Sink] = [narrator, *extra_sinks]
    sinks.append(mcap)
    pipeline = Pipeline(config, sinks)
    clock = EpochClock()
    queue = ReadQueue(pipeline, idle=mcap.write_pending)
    sources += [SerialSource(s, queue, loop, clock) for s in config.sources]
    _announce(config, where, log_dir)
    zenoh_link = ZenohLink(config, pipeline, loop)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    notifier = Notifier()
    period_s = config.status_period_ns / 1e9
    tick_s = min(0.5, period_s / 2, notifier.watchdog_s or 0.5)
    started = loop.time()
    try:
        for source in sources:
            source.start()
        notifier.notify("READY=1", f"STATUS={_summary(sources, pipeline)}")
        deadline = None if duration_s is None else loop.time() + duration_s
        next_status = loop.time() + 1.0
        while not stop.is_set() and queue.failure is None:
            pipeline.extra_status["sources"] = {
                s.cfg.name: {"port": s.cfg.port, "state": s.info.state, "opens": s.info.opens,
                             "losses": s.info.losses, "bytes": s.info.bytes_read,
                             "last_error": s.info.last_error} for s in sources}
            pipeline.extra_status["log"] = {
                "files": [str(f) for f in mcap.files], "error": mcap.error,
                "records_lost": mcap.records_lost, "bad_records": mcap.bad_records}
            queue.flush()  # what waited goes in before a status on the wall clock
            zenoh_link.retry()
            try:
                pipeline.tick(clock.now_ns())
            except Exception as err:
                queue.fail(err, "writing the status")
            if notifier.watchdog_s is not None and queue.failure is None:
                notifier.notify("WATCHDOG=1")
            if loop.time() >= next_status:
                next_status += 1.0
                notifier.notify(f"STATUS={_summary(sources, pipeline)}")
            timeout = tick_s if deadline is None else min(tick_s, deadline - loop.time())
            if timeout <= 0:
                break
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), timeout)
    finally:
        notifier.notify("STOPPING=1", "STATUS=stopping: finishing the log")
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
            signal.signal(sig, signal.SIG_IGN)  # the stop is under way: finish it
        for source in sources:
            source.close()
        queue.flush()
        if queue.failure is None:
            try:
                pipeline.finish()
            except Exception as err:
                queue.fail(err, "finishing")
        pipeline.close()  # each sink's close is guarded: the log is finished whatever came
        notifier.close()
        never = [s for s in sources if not s.info.opens]
        if len(never) == len(sources):
            never = []  # the caller says it: nothing could be opened
        LOG.info("stopped after %.1f s: %d poses; logs: %s", loop.time() - started,
                 pipeline.poses, ", ".join(str(f) for f in mcap.files) or "none")
        for source in never:
            LOG.warning("%s was never opened: %s", source.cfg.name, source.info.last_error)
    if queue.failure is not None:
        raise PipelineError(f"the pipeline failed: {type(queue.failure).__name__}: "
                              f"{queue.failure}") from queue.failure
    return pipeline


class ZenohLink:
    """The Zenoh sink, started with the daemon, or later: a client whose router is not up
    yet (a robot booting before the router), or a listen port still taken, is tried again
    every ``ZENOH_RETRY_S`` while fusion and logging go on."""

    def __init__(self, config: Config, pipeline: Pipeline,
                 loop: asyncio.AbstractEventLoop) -> None:
        self.config = config
        self.pipeline = pipeline
        self.loop = loop
        self.sink: ZenohSink | None = None
        self._next_try = loop.time()
        self._said = ""
        if config.zenoh.get("enabled", True):
            self.retry()

    def retry(self) -> None:
        if (self.sink is not None or not self.config.zenoh.get("enabled", True)
                or self.loop.time() < self._next_try):
            return
        self._next_try = self.loop.time() + ZENOH_RETRY_S
        c = self.config
        try:
            self.sink = ZenohSink(c.zenoh, c.zenoh_prefix, c.nav_frame_id)
        except zenoh.ZError as err:
            reason = zenoh_reason(err)
            if reason != self._said:
                self._said = reason
                LOG.error("zenoh not started: %s; check [zenoh] listen/connect (is the router "
                          "up?); trying again every %.0f s, fusion and the log go on", reason,
                          ZENOH_RETRY_S)
            self.pipeline.extra_status["zenoh"] = {"state": "not started", "error": reason}
            return
        self.pipeline.add_sink(self.sink)
        self.pipeline.extra_status["zenoh"] = {"state": "up", "error": ""}
        if self._said:
            LOG.info("zenoh started: publishing on %s/pose", self.sink.prefix)


def _announce(config: Config, where: str, log_dir: Path) -> None:
    """The start-up summary: config, sources, anchors, Zenoh, log."""
    LOG.info("starting uwbd %s with %s (fusion: %s)", __version__,
             where or "the built-in config", native.implementation)
    for s in config.sources:
        LOG.info("source %s: %s on %s at %d baud", s.name, s.driver, s.port, s.baud)
    anchors = "; ".join(f"{a} ({x:.2f}, {y:.2f}, {z:.2f})"
                        for a, (x, y, z) in sorted(config.anchors_m.items()))
    LOG.info("anchors: %s", anchors or "none configured (taken from the tag's reports)")
    f = config.filter_config()
    LOG.info("fusion: %s, range σ %.3f m, poses at %.0f Hz, status every %.1f s",
             f.mode.value, f.range_sigma_m, 1e9 / config.pose_period_ns,
             config.status_period_ns / 1e9)
    if config.zenoh.get("enabled", True):
        z = config.zenoh
        LOG.info("zenoh %s: keys %s/{pose,status,alive}; listen %s; connect %s; multicast "
                 "scouting %s", z.get("mode", "peer"), config.zenoh_prefix,
                 ", ".join(z.get("listen", [])) or "default", ", ".join(z.get("connect", []))
                 or "none", "on" if z.get("multicast_scouting", True) else "off")
    else:
        LOG.info("zenoh: disabled in the config")
    LOG.info("logs: %s", log_dir.resolve())


def _reason(err: Exception) -> str:
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


def _summary(sources: list[SerialSource], pipeline: Pipeline) -> str:
    """One line for ``systemctl status``."""
    ports = ", ".join(f"{s.cfg.name} {s.info.state}" for s in sources)
    errors = [getattr(k, "error", "") for k in pipeline.sinks if getattr(k, "error", "")]
    return f"{ports}; {pipeline.filter.status}; {pipeline.poses} poses" + (
        f"; {errors[0]}" if errors else "")
