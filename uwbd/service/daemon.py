"""``uwbd run``: serial ports → pipeline → MCAP (and, with the Zenoh sink, the network).

The serial ports (opened, read, stamped, held until they matter, reopened when lost) are
:mod:`uwbd.service.ports`'. SIGINT and SIGTERM stop the loop and finish the log.

The status is published on the wall clock, whether or not data arrives. The systemd
watchdog is fed by the loop's tick, so a hung loop is restarted; an exception out of the
pipeline (a bug: bad input is counted, never raised) is logged, the log finished, and the
run ends with :class:`PipelineError` (exit code 1, so systemd restarts it).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import zenoh

from uwbd import __version__, journal
from uwbd.config import Config
from uwbd.config.model import ROTATE_MB, ROTATE_MINUTES, STALL_AFTER_S
from uwbd.config.zenoh_session import effective, zenoh_reason
from uwbd.fusion.core import native
from uwbd.logs.sink import McapSink
from uwbd.service.narrator import Narrator
from uwbd.service.notify import Notifier
from uwbd.service.pipeline import Pipeline, Sink
from uwbd.service.ports import EpochClock, ReadQueue, SerialSource
from uwbd.service.reads import LoopReads, ThreadReads, make_reads
from uwbd.service.zenohsink import ZenohSink

if TYPE_CHECKING:
    from uwbd.ros2.publisher import Ros2Sink

ZENOH_RETRY_S = 5.0
PROBE_EVERY_S = 5.0  # does the router hold this daemon's liveliness token? (ZenohSink.probe)
LOG = journal.get("daemon")




class PipelineError(RuntimeError):
    """The pipeline raised: the run stopped (its log is finished)."""


class ZenohStartError(RuntimeError):
    """Zenoh cannot start as configured (a listen endpoint taken, a setting Zenoh refuses):
    the daemon does not run without it. A router not reachable yet is not this: that is
    retried."""


# what Zenoh says of a client or peer that reaches none of its connect endpoints yet
NOT_REACHED = "Unable to connect to any of"


async def run(config: Config, log_dir: Path, duration_s: float | None = None,
              extra_sinks: tuple[Sink, ...] = (),
              on_log: Callable[[McapSink], None] | None = None,
              summary_s: float = 60.0, where: str = "") -> Pipeline:
    """Run until SIGINT/SIGTERM (or ``duration_s``); returns the finished pipeline.
    ``on_log`` is handed the log sink first, for callers with more to log (the demo: truth).
    ``summary_s``: how often a health line is logged; ``where``: the config's file name.
    Raises :class:`PipelineError` (after finishing the log) if the pipeline raised."""
    loop = asyncio.get_running_loop()
    rotate_mb = config.log.get("rotate_mb", ROTATE_MB)
    rotate_min = config.log.get("rotate_minutes", ROTATE_MINUTES)
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
    zenoh_link = ZenohLink(config, pipeline, loop)  # (raises ZenohStartError: no run)
    clock = EpochClock()
    queue = ReadQueue(pipeline, idle=mcap.write_pending)
    reads = make_reads(loop, clock, queue)
    sources += [SerialSource(s, queue, loop, clock, reads) for s in config.sources]
    _announce(config, where, log_dir, reads)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    notifier = Notifier()
    period_s = config.status_period_ns / 1e9
    stall_after_ns = int(config.pipeline.get("stall_after_s", STALL_AFTER_S) * 1e9)
    # a tick at least four times per stall time: a stall is said within a quarter of it
    tick_s = min(0.5, period_s / 2, notifier.watchdog_s or 0.5, stall_after_ns / 4e9)
    started = loop.time()
    # what start-up made (modules, config, pipeline) lives as long as the daemon: the cyclic
    # garbage collector leaves it be, so a full collection takes a few ms, not ~30
    gc.freeze()
    try:
        for source in sources:
            source.start()
        notifier.notify("READY=1", f"STATUS={_summary(sources, pipeline)}")
        deadline = None if duration_s is None else loop.time() + duration_s
        next_status = loop.time() + 1.0
        while not stop.is_set() and queue.failure is None:
            reads.drain()  # what the reader thread holds, before a status on the wall clock
            _note_dropped(reads, pipeline)
            now_ns = clock.now_ns()
            for source in sources:
                source.check_stall(now_ns, stall_after_ns)
                source.batch_reads(now_ns, config.pose_period_ns)
            pipeline.extra_status["sources"] = {
                s.cfg.name: {"port": s.cfg.port, "state": s.info.state, "opens": s.info.opens,
                             "losses": s.info.losses, "stalls": s.info.stalls,
                             "bytes": s.info.bytes_read,
                             "read_batch_bytes": s.info.read_batch_bytes,
                             "last_error": s.info.last_error} for s in sources}
            pipeline.extra_status["log"] = {
                "files": [str(f) for f in mcap.files], "error": mcap.error,
                "records_lost": mcap.records_lost, "bad_records": mcap.bad_records}
            queue.flush()  # and what waited in the queue
            zenoh_link.retry()
            zenoh_link.watch()
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
        reads.drain()
        reads.close()
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
        self.ros2: Ros2Sink | None = None
        self._next_try = loop.time()
        self._said = ""
        self._reach = effective(config.zenoh)  # (with its Zenoh file's keys)
        self._next_probe = loop.time()
        self._unheld = 0  # probes in a row that found no router holding the token
        if config.zenoh.get("enabled", True):
            self.retry()
            reason = self.pipeline.extra_status.get("zenoh", {}).get("error", "")
            if self.sink is None and NOT_REACHED not in reason:
                hint = ("another process listens there (another uwbd, or a Zenoh router): "
                        "give [zenoh] listen another endpoint, or connect to that router"
                        if "Address already in use" in reason else
                        "check [zenoh] and its Zenoh file")
                raise ZenohStartError(f"zenoh cannot start as configured: {reason}; {hint}")

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
            if reason != self._said and (self._said or NOT_REACHED in reason):
                LOG.error("zenoh not started: %s; check [zenoh] connect (is the router "
                          "up?); trying again every %.0f s, fusion and the log go on", reason,
                          ZENOH_RETRY_S)
            self._said = reason
            self.pipeline.extra_status["zenoh"] = {"state": "not started", "error": reason}
            return
        self.pipeline.add_sink(self.sink)  # first: the JSON pose leaves before the ROS 2 ones
        if c.ros2_settings.enabled:
            self._start_ros2()
        self.pipeline.extra_status["zenoh"] = {"state": "up", "error": ""}
        if self._said:
            LOG.info("zenoh started: publishing on %s/pose", self.sink.prefix)
        self._said = ""

    def _start_ros2(self) -> None:
        """The ROS 2 topics on the session just opened; if they cannot be declared, said,
        and the JSON keys go on without them."""
        from uwbd.ros2.publisher import Ros2Sink  # noqa: PLC0415 - the ros2 extra, when on

        assert self.sink is not None
        s = self.config.ros2_settings
        try:
            self.ros2 = Ros2Sink(self.sink.session, self.config)
        except Exception as err:  # a ROS 2 problem never stops fusion, the log or Zenoh
            reason = (zenoh_reason(err) if isinstance(err, zenoh.ZError)
                      else f"{type(err).__name__}: {err}")
            LOG.error("ROS 2 topics not started: %s; the poses go on as JSON on %s/pose",
                      reason, self.sink.prefix)
            self.pipeline.extra_status["ros2"] = {"state": "not started", "error": reason}
            return
        self.pipeline.add_sink(self.ros2)
        self.sink.close_first.append(self.ros2.close)  # its declarations, then the session
        LOG.info("ROS 2 over rmw_zenoh (%s): domain %d (%s), node %s, topics %s", s.distro,
                 s.domain_id, s.domain_from, s.node_path, ", ".join(s.published.values()))
        self._ros2_status()

    def _ros2_status(self) -> None:
        if self.ros2 is not None:
            s = self.ros2.settings
            self.pipeline.extra_status["ros2"] = {
                "state": "up", "domain_id": s.domain_id,
                "node": s.node_path,
                "published": self.ros2.counts()}

    def watch(self) -> None:
        """Who the session reaches (routers, peers), in the status; where it is to reach a
        router or peer (``connect``, or client mode) and reaches none, the state is
        ``disconnected`` and one line says so, and another when it is back."""
        if self.sink is None:
            return
        self._ros2_status()
        error = ""
        try:
            info = self.sink.session.info
            routers, peers = len(list(info.routers_zid())), len(list(info.peers_zid()))
        except zenoh.ZError as err:  # a session closing under us: said as such
            routers, peers, error = 0, 0, zenoh_reason(err)
        z = self._reach
        expects = bool(z["connect"]) or z["mode"] == "client"
        state = "disconnected" if expects and routers + peers == 0 else "up"
        if state == "up" and routers and self._refused(error):
            state = "refused"
        before = self.pipeline.extra_status.get("zenoh", {}).get("state")
        if state != before and before in ("up", "disconnected", "refused"):
            if state == "disconnected":
                LOG.warning("zenoh: no router or peer reached (connect %s): poses reach no "
                            "one off this process; Zenoh keeps trying",
                            ", ".join(z.get("connect", [])) or "by scouting")
            elif state == "refused":
                LOG.warning("zenoh: the router does not hold this daemon's liveliness token "
                            "%s/alive: its access control refuses this daemon's keys, and "
                            "drops every pose and status put on them (as shipped it admits a "
                            "certificate's puts on uwbd/<its common name>/** only: is [robot] "
                            "name the certificate's?)", self.config.zenoh_prefix)
            elif before == "refused":
                LOG.info("zenoh: the router admits this daemon's keys again")
            else:
                LOG.info("zenoh: connected again (%d router(s), %d peer(s))", routers, peers)
        self.pipeline.extra_status["zenoh"] = {"state": state, "error": error,
                                               "routers": routers, "peers": peers}

    def _refused(self, error: str) -> bool:
        """Two probes in a row found no router holding the token (one may race a reconnect);
        a probe every ``PROBE_EVERY_S``."""
        assert self.sink is not None
        if error:
            return False
        holders = self.sink.token_holders
        if holders is not None:
            self._unheld = self._unheld + 1 if holders < 2 else 0
            self.sink.token_holders = None
        if self.loop.time() >= self._next_probe:
            self._next_probe = self.loop.time() + PROBE_EVERY_S
            with contextlib.suppress(zenoh.ZError):
                self.sink.probe(PROBE_EVERY_S / 2)
        return self._unheld >= 2


def _announce(config: Config, where: str, log_dir: Path,
              reads: LoopReads | ThreadReads) -> None:
    """The start-up summary: config, sources, anchors, Zenoh, log."""
    LOG.info("starting uwbd %s with %s (fusion: %s; serial reads: %s)", __version__,
             where or "the built-in config", native.implementation, reads.name)
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
        z = effective(config.zenoh)
        LOG.info("zenoh %s: keys %s/{pose,status,alive}; listen %s; connect %s; multicast "
                 "scouting %s%s", z["mode"], config.zenoh_prefix,
                 ", ".join(z["listen"]) or "none", ", ".join(z["connect"]) or "none",
                 "on" if z["multicast_scouting"] else "off",
                 f" (with {config.zenoh['config']})" if "config" in config.zenoh else "")
    else:
        LOG.info("zenoh: disabled in the config")
    LOG.info("logs: %s", log_dir.resolve())


def _note_dropped(reads: LoopReads | ThreadReads, pipeline: Pipeline) -> None:
    """Reads the reader thread could not hold (the loop took none for 64 MB: it hung) are
    counted in the status and said once."""
    dropped = reads.dropped_bytes
    if dropped and "reads_dropped_bytes" not in pipeline.extra_status:
        LOG.error("the serial reader dropped %d bytes: the event loop took no reads for 64 MB "
                  "(is the machine overloaded?)", dropped)
    if dropped:
        pipeline.extra_status["reads_dropped_bytes"] = dropped


def _summary(sources: list[SerialSource], pipeline: Pipeline) -> str:
    """One line for ``systemctl status``."""
    ports = ", ".join(f"{s.cfg.name} {s.info.state}" for s in sources)
    errors = [getattr(k, "error", "") for k in pipeline.sinks if getattr(k, "error", "")]
    return f"{ports}; {pipeline.filter.status}; {pipeline.poses} poses" + (
        f"; {errors[0]}" if errors else "")
