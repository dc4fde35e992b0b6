"""The pipeline core: bytes → drivers → aligner → filter → sinks, one synchronous call per read.

``uwbd run`` calls :meth:`Pipeline.on_bytes` for every read from a serial port, ``uwbd
replay`` for every ``/raw/<source>`` message of a log, in log order with its logged time:
the same code in the same order, so a replay reproduces the live poses bit for bit. Logs
that carry only decoded frames go in through :meth:`Pipeline.on_frame`.

Poses leave after every UWB update and, between updates, at most every
``pose_period_ns`` of data time; status every ``status_period_ns``. Sinks receive
everything (raw bytes, frames, poses, status); one that fails does not stop the others.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Any, Protocol

from drivers import PARSERS, Frame, ImuSample, Parser
from uwbd import __version__
from uwbd.config import Config
from uwbd.fusion.filter import Filter
from uwbd.fusion.types import Pose
from uwbd.service.aligner import Aligner


class Sink(Protocol):
    def raw(self, source: str, t_ns: int, data: bytes) -> None: ...

    def frame(self, frame: Frame) -> None: ...

    def pose(self, pose: Pose) -> None: ...

    def status(self, t_ns: int, status: dict[str, Any]) -> None: ...

    def close(self) -> None: ...


class Pipeline:
    def __init__(self, config: Config, sinks: Sequence[Sink]) -> None:
        self.config = config
        self.sinks = list(sinks)
        self.parsers: dict[str, Parser] = {s.name: PARSERS[s.driver]() for s in config.sources}
        self.aligner = Aligner(config.aligner_wait_ns)
        self.filter = Filter(config.filter_config())
        self.poses = 0
        self.unknown_sources = 0
        self.extra_status: dict[str, Any] = {}  # e.g. port states, set by the runner
        self._last_pose_ns = -(2**63)
        self._period_ns: dict[str, int] = {}  # per source, learned sample period
        self._last_frame_ns: dict[str, int] = {}
        self._last_status_ns: int | None = None

    @property
    def next_pose_due_ns(self) -> int:
        """From this data time on, the next IMU sample brings a pose out."""
        return self._last_pose_ns + self.config.pose_period_ns

    def on_bytes(self, source: str, t_ns: int, data: bytes) -> None:
        """One read of ``data`` from ``source`` whose last byte arrived at ``t_ns``."""
        parser = self.parsers.get(source)
        if parser is None:
            self.unknown_sources += 1
            return
        for sink in self.sinks:
            sink.raw(source, t_ns, data)
        self._frames(self._spread(source, parser.feed(data, t_ns)))
        self._tick(t_ns)

    def _spread(self, source: str, frames: Sequence[Frame]) -> Sequence[Frame]:
        """Give the samples of one read their own times.

        A read's receive time is exact only for its last frame; when one read holds several
        frames of a source (the port was read late), the earlier ones arrived about one
        sample period apart before it. Without this they share one time and the filter
        must drop all but one. The period is learned per source from successive reads that
        hold one frame each; spread times never fall back to or before the source's previous
        frame. Deterministic: replay spreads the logged reads the same way.
        """
        previous = self._last_frame_ns.get(source)
        if len(frames) == 1:
            t = frames[0].t_ns
            if previous is not None and t > previous:
                old = self._period_ns.get(source)
                delta = t - previous
                self._period_ns[source] = delta if old is None else (7 * old + delta) // 8
        elif frames and source in self._period_ns:
            period, n, floor = self._period_ns[source], len(frames), previous
            spread = []
            for k, f in enumerate(frames):
                t = f.t_ns - (n - 1 - k) * period
                if floor is not None and t <= floor:
                    t = floor + 1
                floor = t
                spread.append(dataclasses.replace(f, t_ns=min(t, f.t_ns)))
            frames = spread
        if frames:
            self._last_frame_ns[source] = frames[-1].t_ns
        return frames

    def on_frame(self, frame: Frame) -> None:
        """A decoded frame (logs without raw channels)."""
        self._frames([frame])
        self._tick(frame.t_ns)

    def finish(self) -> None:
        """End of input: parsers and aligner give up what they hold; a last status."""
        for parser in self.parsers.values():
            self._frames(parser.flush())
        for frame in self.aligner.flush():
            self._fuse(frame)
        if self._last_status_ns is not None:
            self._emit_status(self._last_status_ns)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()

    def _frames(self, frames: Sequence[Frame]) -> None:
        for frame in frames:
            for sink in self.sinks:
                sink.frame(frame)
            for ready in self.aligner.push(frame):
                self._fuse(ready)

    def _fuse(self, frame: Frame) -> None:
        flt = self.filter
        if isinstance(frame, ImuSample):
            flt.predict(frame)
            if frame.t_ns - self._last_pose_ns < self.config.pose_period_ns:
                return
        else:
            flt.update(frame)
        pose = flt.pose()
        if pose is not None:
            self._last_pose_ns = pose.t_ns
            self.poses += 1
            for sink in self.sinks:
                sink.pose(pose)

    def _tick(self, t_ns: int) -> None:
        if self._last_status_ns is None:
            self._last_status_ns = t_ns
        elif t_ns - self._last_status_ns >= self.config.status_period_ns:
            self._last_status_ns = t_ns
            self._emit_status(t_ns)

    def _emit_status(self, t_ns: int) -> None:
        status = self.status(t_ns)
        for sink in self.sinks:
            sink.status(t_ns, status)

    def status(self, t_ns: int) -> dict[str, Any]:
        """Filter health, gating counts, parser and aligner statistics."""
        flt = self.filter
        pose = flt.pose()
        out: dict[str, Any] = {
            "t_ns": t_ns, "version": __version__, "filter": flt.status, **flt.diagnostics(),
            "heading_observable": bool(pose and pose.heading_observable),
            "poses": self.poses, "fusion_counters": dict(flt.counters),
            "gating_rejections": dict(flt.gating.rejections),
            "aligner": self.aligner.stats(),
            "parsers": {name: _brief(p) for name, p in self.parsers.items()},
        }
        if self.unknown_sources:
            out["unknown_source_reads"] = self.unknown_sources
        out.update(self.extra_status)
        for sink in self.sinks:
            problem = getattr(sink, "error", "")
            if problem:
                out.setdefault("sink_errors", []).append(problem)
        return out


def _brief(parser: Parser) -> dict[str, Any]:
    stats = parser.stats.as_dict()
    recent = stats.pop("recent_errors")
    stats["last_error"] = recent[-1] if recent else ""
    return stats


class PoseList:
    """A sink that keeps the poses (replay comparisons, tests)."""

    def __init__(self) -> None:
        self.poses: list[Pose] = []
        self.statuses: list[dict[str, Any]] = []

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        """Raw bytes are not kept."""

    def frame(self, frame: Frame) -> None:
        """Frames are not kept."""

    def pose(self, pose: Pose) -> None:
        self.poses.append(pose)

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        self.statuses.append(status)

    def close(self) -> None:
        """Nothing to release."""


def monotonic_pacer(start_log_ns: int) -> Any:
    """For ``--realtime``: a function that sleeps until a log time is due, paced from one
    start instant so no drift builds up."""
    start = time.monotonic_ns()

    def wait_for(t_ns: int) -> None:
        delay = (t_ns - start_log_ns) - (time.monotonic_ns() - start)
        if delay > 0:
            time.sleep(delay / 1e9)
    return wait_for
