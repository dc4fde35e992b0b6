"""The common IMU read in one call of the C core (uwbd/fusion/_imu_read.c) against the Python
path it stands for: the same reads through two pipelines, one with it and one without, give
the same poses, frames and status, and leave every object it touches in the same state.

The streams are made to leave the common case often (line faults, saturated and jumping
samples, time going back, a gap, a stretch without ranges, calibrated and dead-banded gyros,
a held aligner), so that every place where the core declines is crossed both ways.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import pytest

from drivers.emulator.faults import FaultCounts, Faults, Window, inject
from drivers.frames import ImuSample, UwbRanges
from drivers.nlink import encode as encode_nlink
from drivers.wit import encode as encode_wit
from uwbd.config import apply_overrides, parse
from uwbd.fusion import native
from uwbd.fusion.filter import Filter
from uwbd.service.pipeline import Pipeline, PoseList
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import SimConfig, simulate

needs_core = pytest.mark.skipif(native.core is None, reason=native.implementation)
Read = tuple[str, int, bytes]


class Recorder(PoseList):
    """Poses and statuses (PoseList) and every frame too."""

    def __init__(self) -> None:
        super().__init__()
        self.frames: list[object] = []

    def frame(self, frame: object) -> None:  # (it has no read: the pipeline calls this)
        self.frames.append(frame)


def reads(seconds: float, seed: int, faults: Faults | None = None,
          edit: Callable[[ImuSample, int], ImuSample | None] | None = None,
          no_ranges: tuple[float, float] | None = None) -> tuple[str, list[Read]]:
    """A simulated run's reads (config, [(source, t_ns, bytes)]): the IMU's through the
    fault injector, each sample first through ``edit`` (``None`` drops it), the tag's epochs
    left out over ``no_ranges`` (from, to s)."""
    sim = simulate(SimConfig(seed=seed, segments=((3.0, 0.0, 0.0, 0.0),
                                                  (seconds - 3.0, 1.0, 0.4, 0.0))))
    t0 = sim.imu[0].t_ns
    imu = []
    for k, sample in enumerate(sim.imu):
        edited = sample if edit is None else edit(sample, k)
        if edited is not None:
            imu.append((edited.t_ns - t0, encode_wit(edited)))
    events = [(t0 + t, "imu", data) for t, data in
              inject(imu, faults or Faults(), 921600, seed, FaultCounts()) if data]
    for uwb in sim.uwb:
        s = (uwb.t_ns - t0) / 1e9
        if no_ranges is None or not no_ranges[0] <= s < no_ranges[1]:
            events.append((uwb.t_ns, "uwb", encode_nlink(uwb)))
    events.sort(key=lambda e: e[0])
    return simulation_toml(sim), [(source, t, data) for t, source, data in events]


def run(toml: str, stream: list[Read], how: str) -> tuple[Pipeline, Recorder, int]:
    """The stream through a pipeline: ``"read"`` with the C core's read path (and step),
    ``"step"`` with its filter step only, ``"python"`` with neither (the reference; the C
    core's algebra in both). Returns how many IMU reads (or samples) C took whole."""
    sink = Recorder()
    pipeline = Pipeline(parse(toml), [sink])
    taken = 0

    def counted(call: Any) -> Any:
        def wrapper(*args: Any) -> Any:
            nonlocal taken
            out = call(*args)
            taken += out is not None
            return out
        return wrapper
    if how == "read":
        assert pipeline._imu_read, "the pipeline made no read path for the WitMotion IMU"
        pipeline._imu_read["imu"] = counted(pipeline._imu_read["imu"])
    else:
        pipeline._imu_read.clear()
        flt = pipeline.filter
        flt.imu_step = counted(flt.imu_step) if how == "step" else None
    for source, t_ns, data in stream:
        pipeline.on_bytes(source, t_ns, data)
    pipeline.finish()
    return pipeline, sink, taken


def state(pipeline: Pipeline) -> dict[str, Any]:
    """Everything the read path reads or writes, as comparable values."""
    flt = pipeline.filter
    ekf = flt.ekf
    return {
        "parser": {k: v for k, v in vars(pipeline.parsers["imu"]).items() if k != "stats"},
        "stats": pipeline.parsers["imu"].stats.as_dict(),
        "spread": (pipeline._last_frame_ns, pipeline._period_ns),
        "aligner": (pipeline.aligner._clock_ns, pipeline.aligner._released_ns,
                    pipeline.aligner.stats()),
        "check": vars(flt.imu_check),
        "window": (list(flt.window.samples), flt.window._added),
        "filter": (flt.t_ns, flt._imu_t_ns, flt._first_t_ns, flt._good_imu_ns, flt._last_imu,
                   dict(flt.counters), flt.status),
        "ekf": None if ekf is None else (ekf.p, ekf.v, ekf.q, ekf.interval_s, ekf._sum_fn,
                                         ekf._sum_w, ekf.P.tobytes()),
    }


def same_runs(toml: str, stream: list[Read], min_taken: float = 0.5) -> int:
    """The C read path, and the C step alone, each against the reference; the read path must
    have taken ``min_taken`` of the IMU reads (the step at least as many)."""
    slow, slow_sink, _ = run(toml, stream, "python")
    assert len(slow_sink.poses) > 0
    imu_reads = sum(source == "imu" for source, _, _ in stream)
    taken = {}
    for how in ("read", "step"):
        fast, fast_sink, taken[how] = run(toml, stream, how)
        assert fast_sink.poses == slow_sink.poses, how
        assert fast_sink.frames == slow_sink.frames, how
        assert fast_sink.statuses == slow_sink.statuses, how
        assert state(fast) == state(slow), how
    assert taken["read"] >= min_taken * imu_reads, \
        f"the read path took {taken['read']} of {imu_reads} reads"
    assert taken["step"] >= taken["read"]
    return taken["read"]


@needs_core
def test_a_clean_run_is_taken_whole_and_the_same() -> None:
    toml, stream = reads(12.0, seed=1)
    taken = same_runs(toml, stream, min_taken=0.9)
    assert taken < sum(s == "imu" for s, _, _ in stream)  # the first samples are Python's


@needs_core
@pytest.mark.parametrize("split", [False, True])
def test_line_faults_are_left_to_python_and_the_rest_the_same(split: bool) -> None:
    """Garbage, flipped bytes, lost and stalled frames; and every frame written in pieces,
    which no read then holds whole (the Python path takes them all)."""
    faults = Faults(garbage_rate_hz=3.0, split=split, corrupt_prob=0.02, drop_prob=0.02,
                    stalls=(Window(6.0, 0.3),))
    same_runs(*reads(12.0, seed=2, faults=faults), min_taken=0.0 if split else 0.5)


def _faulty(sample: ImuSample, k: int) -> ImuSample | None:
    """Samples the check rejects (saturated, jumps, not finite on the wire is impossible:
    int16s), times that go back or repeat, a gap longer than the filter bridges."""
    if 1700 <= k < 2100:  # about a second without the IMU
        return None
    if k % 397 == 50:  # saturated on x
        return dataclasses.replace(sample, acc_mps2=(156.0, *sample.acc_mps2[1:]))
    if k % 211 == 20:  # a jump of the accelerometer (~10 g), then back
        return dataclasses.replace(sample, acc_mps2=(100.0, *sample.acc_mps2[1:]))
    if k % 293 == 7:  # time goes back by a sample
        return dataclasses.replace(sample, t_ns=sample.t_ns - 7_000_000)
    if k % 331 == 9:  # the same time twice
        return dataclasses.replace(sample, t_ns=sample.t_ns - 5_000_000)
    return sample


@needs_core
def test_rejected_samples_times_out_of_order_and_a_gap_are_the_same() -> None:
    fast, _, _ = run(*reads(12.0, seed=3, edit=_faulty), "read")
    for counter in ("imu_saturated", "imu_jump", "imu_out_of_order", "imu_gaps"):
        assert fast.filter.counters[counter] > 0, counter  # each case was met
    same_runs(*reads(12.0, seed=3, edit=_faulty), min_taken=0.7)


@needs_core
def test_a_stretch_without_ranges_propagates_the_same() -> None:
    """Without updates the covariance follows every 0.1 s of samples: the read path hands
    that back (Filter.finish_prediction)."""
    same_runs(*reads(12.0, seed=4, no_ranges=(7.0, 9.0)), min_taken=0.8)


@needs_core
@pytest.mark.parametrize("sets", [
    ["imu.acc_scale=[1.01, 0.99, 1.002]", "imu.acc_offset_mps2=[0.05, -0.03, 0.1]",
     "imu.gyro_offset_rps=[0.001, -0.002, 0.0005]"],
    ["imu.gyro_offset_rps=[0.001, -0.002, 0.0005]", "imu.gyro_deadband_rps=0.01"],
    ["pipeline.aligner_wait_ms=20"],
])
def test_calibrations_and_a_waiting_aligner_are_the_same(sets: list[str]) -> None:
    toml, stream = reads(8.0, seed=5)
    toml = apply_overrides(toml, sets, "test")
    waiting = any(s.startswith("pipeline.aligner_wait") for s in sets)
    same_runs(toml, stream, min_taken=0.0 if waiting else 0.8)


@needs_core
def test_the_path_is_made_only_for_witmotion_with_the_core() -> None:
    toml, _ = reads(4.0, seed=6)
    assert set(Pipeline(parse(toml), [])._imu_read) == {"imu"}
    with native.pure_python():
        assert Pipeline(parse(toml), [])._imu_read == {}


@needs_core
def test_a_read_the_path_declines_changes_nothing() -> None:
    """Anything but the common cycle in order comes back ``None``, with no state changed;
    then the read itself is taken."""
    toml, stream = reads(6.0, seed=7)
    pipeline = Pipeline(parse(toml), [])
    for source, t_ns, data in stream[:200]:
        pipeline.on_bytes(source, t_ns, data)
    before = state(pipeline)
    source, t_ns, data = next(r for r in stream[200:] if r[0] == "imu")
    path = pipeline._imu_read["imu"]
    broken_sum = data[:10] + bytes(((data[10] + 1) & 0xFF,)) + data[11:]
    for bad in (data[:21], data + b"\x55", broken_sum, data[11:] + data[:11], data[:2] * 11):
        assert path(bad, t_ns) is None, bad.hex()
    assert path(bytearray(data), t_ns) is None  # bytes only
    assert path(data, before["filter"][1]) is None  # not after the last sample
    assert path(data, 2**62 + 1) is None  # a time no difference of which fits in int64
    ekf = pipeline.filter.ekf
    assert ekf is not None
    p = ekf.p
    ekf.p = tuple(p)  # type: ignore[assignment]  # a state the INS step cannot write in place
    assert path(data, t_ns) is None
    ekf.p = p
    assert state(pipeline) == before
    assert path(data, t_ns) is not None
    assert state(pipeline)["window"][1] == before["window"][1] + 1


@needs_core
def test_a_sample_the_check_rejects_is_left_to_python() -> None:
    """Filter.predict's C step takes only what the check passes: not finite, saturated or
    jumping samples (from any driver) go to the reference, which counts them."""
    toml, stream = reads(6.0, seed=9)
    pipeline = Pipeline(parse(toml), [])
    for source, t_ns, data in stream[:300]:
        pipeline.on_bytes(source, t_ns, data)
    flt = pipeline.filter
    assert flt.imu_step is not None and flt.ekf is not None
    before = state(pipeline)
    t_ns = before["filter"][1] + 5_000_000
    good = (0.1, 0.2, 9.8)
    for acc, gyro in (((math.nan, 0.2, 9.8), (0.0, 0.0, 0.0)), (good, (0.0, math.inf, 0.0)),
                      ((157.0, 0.0, 9.8), (0.0, 0.0, 0.0)), ((90.0, 0.0, 9.8), (0.0, 0.0, 0.0)),
                      ((1, 2, 3), (0.0, 0.0, 0.0))):
        assert flt.imu_step(t_ns, acc, gyro) is None, (acc, gyro)
    last_good, flt.imu_check.last_good = flt.imu_check.last_good, None  # no jump test then
    assert flt.imu_step(t_ns, (math.nan, 0.2, 9.8), (0.0, 0.0, 0.0)) is None
    flt.imu_check.last_good = last_good
    assert state(pipeline) == before
    assert flt.imu_step(t_ns, good, (0.0, 0.0, 0.0)) is not None


@needs_core
@pytest.mark.parametrize("first_t", [True, 1.0, 0])
def test_a_window_row_python_stamped_otherwise_is_compared_as_python_does(
        first_t: object) -> None:
    """A sample the step declined (its time a bool or a float) is in the rest window when
    the next ones are taken: the step ages the window out with Python's own comparison."""
    sim = simulate(SimConfig(seed=1, segments=((3.0, 0.0, 0.0, 0.0),)))
    cfg = parse(simulation_toml(sim)).filter_config()
    acc, gyro = sim.imu[0].acc_mps2, sim.imu[0].gyro_rps
    filters = []
    for use_c in (True, False):
        flt = Filter(cfg)
        if not use_c:
            flt.imu_step = None
        flt.update(UwbRanges(0, ()))  # the data begin with the tag: the first time an int
        for t_ns in (first_t, 5_000_000, 10_000_000, 2_000_000_000):
            flt.predict(ImuSample(t_ns, acc, gyro))  # type: ignore[arg-type]
        filters.append(flt)
    fast, slow = filters
    assert list(fast.window.samples) == list(slow.window.samples)
    assert (fast._imu_t_ns, fast._good_imu_ns, fast._last_imu, vars(fast.imu_check)) == \
        (slow._imu_t_ns, slow._good_imu_ns, slow._last_imu, vars(slow.imu_check))
