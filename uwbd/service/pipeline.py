"""The pipeline core: bytes → drivers → aligner → filter → sinks, one synchronous call per read.

``uwbd run`` calls :meth:`Pipeline.on_bytes` for every read from a serial port, ``uwbd
replay`` for every ``/raw/<source>`` message of a log, in log order with its logged time:
the same code in the same order, so a replay reproduces the live poses bit for bit. Logs
that carry only decoded frames go in through :meth:`Pipeline.on_frame`.

Poses leave at the configured rate (one a ``pose_period_ns`` of data time, from the IMU
samples between updates: after the read that brings the sample a pose falls due at, at
the read's last sample, so that a read of several samples gives its newest state; the next
falls due a period after the slot this one was due in) and after every UWB epoch of several
ranges, whose
correction should not wait; a single range (a DW1000-class tag ranges one anchor at a
time, ~170 a second) updates the state at once but brings a pose out only when one is due;
status every ``status_period_ns``. Sinks receive
everything (raw bytes, frames, poses, status). Each call to a sink
is guarded: a sink that raises is counted and reported (a warning line, ``sink_errors`` in
the status) and the others, the log among them, still get every record.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Any, Protocol

from drivers import PARSERS, Frame, ImuSample, Parser, UwbRanges
from uwbd import __version__, journal
from uwbd.config import Config
from uwbd.fusion.filter import Filter
from uwbd.fusion.types import Pose
from uwbd.service.aligner import Aligner
from uwbd.service.sample_times import SampleTimes, batched_bauds


class Sink(Protocol):
    """What the pipeline hands on."""

    def raw(self, source: str, t_ns: int, data: bytes) -> None: ...

    def frame(self, frame: Frame) -> None: ...

    def pose(self, pose: Pose) -> None: ...

    def status(self, t_ns: int, status: dict[str, Any]) -> None: ...

    def close(self) -> None: ...


LOG = journal.get("pipeline")


@dataclasses.dataclass
class SinkTrouble:
    """How often one sink raised, and the last error."""

    name: str
    failures: int = 0
    last_error: str = ""

    def text(self) -> str:
        return f"{self.name} failed {self.failures}x, last: {self.last_error}"


class Pipeline:
    def __init__(self, config: Config, sinks: Sequence[Sink]) -> None:
        self.config = config
        self.sinks = list(sinks)
        self.sink_trouble: dict[int, SinkTrouble] = {}  # by id(sink)
        self._raw = [s.raw for s in self.sinks]
        self._frame = [s.frame for s in self.sinks]
        self._pose = [s.pose for s in self.sinks]
        self._status = [s.status for s in self.sinks]
        self.parsers: dict[str, Parser] = {s.name: PARSERS[s.driver]() for s in config.sources}
        self.aligner = Aligner(config.aligner_wait_ns)
        self.filter = Filter(config.filter_config())
        self.poses = 0
        self.unknown_sources = 0
        self.bad_records = 0  # decoded log records that are not frames (replay)
        self.extra_status: dict[str, Any] = {}  # e.g. port states, set by the runner
        self._last_pose_ns = -(2**63)
        # the IMU sample of this read at which a pose fell due (it leaves after the read)
        self._due_ns: int | None = None
        self._pose_period_ns = config.pose_period_ns  # a property: read once, not per sample
        self._status_period_ns = config.status_period_ns
        # each read's frames a time of their own
        self.sample_times = SampleTimes(batched_bauds(config.sources))
        self._last_status_ns: int | None = None
        self._latest_ns = -(2**63)  # the latest data (or wall-clock tick) time seen

    @property
    def next_pose_due_ns(self) -> int:
        """From this data time on, the next IMU sample brings a pose out."""
        return self._last_pose_ns + self._pose_period_ns

    def on_bytes(self, source: str, t_ns: int, data: bytes) -> None:
        """One read of ``data`` from ``source`` whose last byte arrived at ``t_ns``."""
        parser = self.parsers.get(source)
        if parser is None:
            self.unknown_sources += 1
            return
        self._raw_to_sinks(source, t_ns, data)
        self._frames(self.sample_times.spread(source, parser.feed(data, t_ns), len(data)))
        if self._due_ns is not None:
            self._emit_pose(self._due_ns)
        self._tick(t_ns)

    def _raw_to_sinks(self, source: str, t_ns: int, data: bytes) -> None:
        for call in self._raw:
            try:
                call(source, t_ns, data)
            except Exception as err:
                self._sink_failed(call, err)

    def on_frame(self, frame: Frame) -> None:
        """A decoded frame (logs without raw channels)."""
        self._frames([frame])
        if self._due_ns is not None:
            self._emit_pose(self._due_ns)
        self._tick(frame.t_ns)

    def finish(self) -> None:
        """End of input: parsers and aligner give up what they hold; a last status."""
        for source, parser in self.parsers.items():  # (a cycle held for its wrap: after the last)
            self._frames(self.sample_times.spread(source, parser.flush()))
        for frame in self.aligner.flush():
            self._fuse(frame)
        if self._due_ns is not None:
            self._emit_pose(self._due_ns)
        if self._last_status_ns is not None:  # at the latest data time: it counts all
            self._emit_status(self._latest_ns)

    def close(self) -> None:
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as err:
                self._sink_failed(sink.close, err)

    def add_sink(self, sink: Sink) -> None:
        """A sink that could only start later (Zenoh once its router is up)."""
        self.sinks.append(sink)
        self._raw.append(sink.raw)
        self._frame.append(sink.frame)
        self._pose.append(sink.pose)
        self._status.append(sink.status)

    def sink_failed(self, call: Any, err: Exception) -> None:
        """A sink (or work done for one, ``call``) raised: counted and said, never passed on."""
        self._sink_failed(call, err)

    def _sink_failed(self, call: Any, err: Exception) -> None:
        """Count and report a sink's exception; the first of each kind is a warning line."""
        sink = getattr(call, "__self__", call)
        trouble = self.sink_trouble.setdefault(id(sink), SinkTrouble(type(sink).__name__))
        text = f"{type(err).__name__}: {err}"
        trouble.failures += 1
        if text != trouble.last_error:
            LOG.warning("sink %s failed in %s: %s (the other sinks go on)", trouble.name,
                        getattr(call, "__name__", "?"), text)
        trouble.last_error = text

    def _frames(self, frames: Sequence[Frame]) -> None:
        """Frames to the sinks and, in time order through the aligner, to the filter: the
        IMU samples that come in a row (a read's) in one call (``Filter.predict_many``)."""
        samples: list[ImuSample] = []
        for frame in frames:
            for call in self._frame:
                try:
                    call(frame)
                except Exception as err:
                    self._sink_failed(call, err)
            for ready in self.aligner.push(frame):
                if ready.__class__ is ImuSample:
                    samples.append(ready)
                    continue
                if samples:
                    self._predict(samples)
                    samples = []
                self._fuse(ready)
        if samples:
            self._predict(samples)

    def _predict(self, samples: list[ImuSample]) -> None:
        """IMU samples in a row; a pose falls due at the first a period after the last."""
        self.filter.predict_many(samples)
        if self._due_ns is None:
            last_ns, period_ns = self._last_pose_ns, self._pose_period_ns
            for sample in samples:
                if sample.t_ns - last_ns >= period_ns:
                    self._due_ns = sample.t_ns  # the pose leaves at the end of the read
                    break

    def _fuse(self, frame: Frame) -> None:
        flt = self.filter
        if isinstance(frame, ImuSample):
            self._predict([frame])
            return
        if not isinstance(frame, UwbRanges):
            return  # anchor-to-anchor ranges: logged for surveying, never fused
        flt.update(frame)
        if len(frame.ranges) >= 2:
            self._emit_pose()
        elif frame.t_ns - self._last_pose_ns >= self._pose_period_ns:
            self._emit_pose(frame.t_ns)  # a single range brings the pose due: on the grid

    def _emit_pose(self, due_ns: int | None = None) -> None:
        """The pose now; the next falls due a period after this one or, for a pose the IMU
        brought (``due_ns``: the sample at which it fell due, inside the read it leaves
        after), a period after the slot it was due in (unless that sample is a period or
        more past it: a gap): on a grid, so that neither reads of a few samples nor
        samples a hair short of the period apart make fewer poses than configured."""
        self._due_ns = None
        pose = self.filter.pose()
        if pose is not None:
            if due_ns is None:
                self._last_pose_ns = pose.t_ns
            else:
                slot_ns = self._last_pose_ns + self._pose_period_ns
                self._last_pose_ns = slot_ns if due_ns - slot_ns < self._pose_period_ns \
                    else due_ns
            self.poses += 1
            for call in self._pose:
                try:
                    call(pose)
                except Exception as err:
                    self._sink_failed(call, err)

    def tick(self, t_ns: int) -> None:
        """The status, if one is due at ``t_ns``: the daemon calls this on the wall clock too,
        so the status goes on while no data arrives."""
        self._tick(t_ns)

    def _tick(self, t_ns: int) -> None:
        if t_ns > self._latest_ns:  # noqa: PLR1730 - max() costs a call, for every read
            self._latest_ns = t_ns
        if self._last_status_ns is None:
            self._last_status_ns = t_ns
        elif t_ns - self._last_status_ns >= self._status_period_ns:
            self._last_status_ns = t_ns
            self._emit_status(t_ns)

    def _emit_status(self, t_ns: int) -> None:
        status = self.status(t_ns)
        for call in self._status:
            try:
                call(t_ns, status)
            except Exception as err:
                self._sink_failed(call, err)

    def status(self, t_ns: int) -> dict[str, Any]:
        """Filter health, gating counts, parser and aligner statistics (``uwbd.Status``)."""
        flt = self.filter
        pose = flt.pose()
        out: dict[str, Any] = {
            "timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
            "t_ns": t_ns, "version": __version__, "filter": flt.health(t_ns).summary(),
            **flt.diagnostics(t_ns),
            "heading_observable": bool(pose and pose.heading_observable),
            "poses": self.poses, "fusion_counters": dict(flt.counters),
            "gating_rejections": dict(flt.gating.rejections),
            "aligner": self.aligner.stats(),
            "parsers": {name: _brief(p) for name, p in self.parsers.items()},
        }
        # a value not known is left out (the JSON schema, uwbd.logs.foxglove, has no nulls)
        out["health"] = {k: v for k, v in out["health"].items() if v is not None}
        if self.unknown_sources:
            out["unknown_source_reads"] = self.unknown_sources
        if self.bad_records:
            out["bad_records"] = self.bad_records
        out.update(self.extra_status)
        for sink in self.sinks:
            problem = getattr(sink, "error", "")
            if problem:
                out.setdefault("sink_errors", []).append(problem)
        for trouble in self.sink_trouble.values():
            out.setdefault("sink_errors", []).append(trouble.text())
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
