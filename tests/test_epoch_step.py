"""The common UWB message and the common pose whole on the C core (``_core.epoch_step``,
uwbd/fusion/_epoch.c; ``_core.pose_step``, uwbd/fusion/_pose.c) against Filter._update and
Filter.pose, their reference: the same reports, poses, counters, health evidence,
anchor statistics, range window and covariance, to the bit, through single ranges, epochs,
faults and both real datasets; and every message it does not take declined with nothing
changed."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.frames import AnchorRange, Frame, ImuSample, UwbRanges
from uwbd.config import parse
from uwbd.fusion import native
from uwbd.fusion.eskf import Eskf
from uwbd.fusion.filter import Filter
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import Pose
from uwbd.tools.evaluate import merge
from uwbd.tools.importer import INROL_LEVER_ARM_M, INROL_MOUNTING, load_iasl, load_inrol
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import Z_DOWN, SimConfig, ceiling_room, handheld_async, simulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
pytestmark = pytest.mark.skipif(native.core is None, reason=f"C core: {native.implementation}")


def state(flt: Filter) -> str:
    """Everything an update writes, as text (NaN compares equal so)."""
    ekf = flt.ekf
    nominal = None if ekf is None else (ekf.p, ekf.v, ekf.q, ekf.b_g, ekf.b_a, ekf._T,
                                        type(ekf._T), ekf._epoch_propagated,
                                        ekf._sum_fn, ekf._sum_w, ekf._dv_epoch,
                                        ekf.P.tolist(), ekf.b_r.tolist(), ekf._Phi_epoch.tolist())
    monitor = {k: list(v) if k == "_outcomes" else v for k, v in vars(flt.monitor).items()}
    return repr((nominal, flt.t_ns, dict(flt.counters), flt.gating, monitor,
                 {a: vars(s) for a, s in flt.anchor_stats.items()}, flt.ranges.latest,
                 [(t, p.tolist()) for t, p in flt.stillness.fixes], flt._fade_ns,
                 flt._constraints_ns, flt._coasted, flt._aligned,
                 None if flt._last_good_P is None else flt._last_good_P.tolist()))


def twins(cfg: FilterConfig) -> tuple[Filter, Filter, list[int]]:
    """Two filters, the first with the C steps (the messages its epoch step took counted),
    the second with the reference alone."""
    fast, slow = Filter(cfg), Filter(cfg)
    slow.epoch_step = slow.pose_step = None
    step, taken = fast.epoch_step, [0, 0, 0]  # taken, declined, taken while aligning
    assert step is not None

    def counted(uwb: UwbRanges) -> Any:
        aligning = fast.ekf is not None and not fast._aligned
        out = step(uwb)
        taken[out is None] += 1
        taken[2] += out is not None and aligning
        return out
    fast.epoch_step = counted
    return fast, slow, taken


def run_both(cfg: FilterConfig, frames: list[Frame], check_every: int = 50) -> list[int]:
    fast, slow, taken = twins(cfg)
    for k, frame in enumerate(frames):
        if isinstance(frame, ImuSample):
            fast.predict(frame)
            slow.predict(frame)
            continue
        a, b = fast.update(frame), slow.update(frame)
        assert repr(a) == repr(b), f"message {k}"
        assert repr(fast.pose()) == repr(slow.pose()), f"message {k}"
        if k % check_every == 0:
            assert state(fast) == state(slow), f"message {k}"
    assert state(fast) == state(slow)
    return taken


@pytest.mark.parametrize("preset", ["handheld", "ceiling", "faults"])
def test_epoch_step_matches_the_reference(preset: str) -> None:
    """Single ranges at ~170 Hz (multipath, restarts of the alignment), epochs under a
    ceiling, and a run through an IMU spike, a saturation, an IMU gap and a UWB outage."""
    if preset == "faults":
        sim = simulate(SimConfig(seed=2, imu_spikes_s=(12.0,),
                                 imu_saturations_s=((16.0, 0.5),), imu_gaps_s=((20.0, 2.0),),
                                 uwb_outages_s=((28.0, 6.0),)))
    else:
        sim = simulate(handheld_async(2) if preset == "handheld" else ceiling_room(2))
    taken, declined, aligning = run_both(parse(simulation_toml(sim)).filter_config(),
                                         list(merge(sim.imu, sim.uwb)))
    assert taken > 4 * declined  # the common message is the C step's
    assert aligning > 50  # (while the heading is held too)


@pytest.mark.skipif(not DATA.is_dir(), reason="shared/data not beside the repository")
@pytest.mark.parametrize("name", ["iasl-s1", "inrol-env1"])
def test_epoch_step_matches_the_reference_on_real_runs(name: str) -> None:
    """The first 40 s of the flight (Nooploop epochs) and of the handheld run (single ranges
    with multipath)."""
    load, mounting, lever = ((load_iasl, Z_DOWN, (0.0, 0.0, 0.0)) if name == "iasl-s1"
                             else (load_inrol, INROL_MOUNTING, INROL_LEVER_ARM_M))
    ds = load(DATA / name)
    frames = list(merge(ds.imu, ds.uwb))
    frames = [f for f in frames if f.t_ns < frames[0].t_ns + 40 * 10**9]
    cfg = FilterConfig(anchors_m=ds.anchors_m, mounting_rotation=mounting, lever_arm_m=lever)
    taken, declined, _ = run_both(cfg, frames)
    assert taken > 2 * declined


@pytest.fixture(scope="module")
def tracking() -> tuple[Filter, list[Frame]]:
    """A filter running and aligned on single ranges, the C step taking them, and the rest
    of its run."""
    sim = simulate(handheld_async(4))
    flt = Filter(parse(simulation_toml(sim)).filter_config())
    frames = list(merge(sim.imu, sim.uwb))
    for k, frame in enumerate(frames):
        if isinstance(frame, ImuSample):
            flt.predict(frame)
        else:
            flt.update(frame)
        if flt._aligned and k > len(frames) // 2:
            return flt, frames[k + 1:]
    raise AssertionError("the filter never aligned")


def _next_message(frames: list[Frame]) -> UwbRanges:
    return next(f for f in frames if isinstance(f, UwbRanges))


def _odd(uwb: UwbRanges, case: str, flt: Filter) -> UwbRanges:
    r = uwb.ranges[0]
    odd: dict[str, Callable[[], UwbRanges]] = {
        "not finite": lambda: _with(uwb, dataclasses.replace(r, range_m=math.nan)),
        "negative": lambda: _with(uwb, dataclasses.replace(r, range_m=-1.0)),
        "too long": lambda: _with(uwb, dataclasses.replace(r, range_m=1e6)),
        "with a quality": lambda: _with(uwb, dataclasses.replace(r, quality=90.0)),
        "unknown anchor": lambda: _with(uwb, dataclasses.replace(r, anchor_id=987)),
        "duplicate anchor": lambda: dataclasses.replace(uwb, ranges=(r, r)),
        "an int range": lambda: _with(uwb, dataclasses.replace(r, range_m=3)),
        "late": lambda: dataclasses.replace(uwb, t_ns=(flt.t_ns or 0) - 10**6),
        "new anchor set": lambda: dataclasses.replace(
            uwb, ranges=tuple(AnchorRange(a, 5.0) for a in sorted(flt._configured)[:2])),
        "no ranges": lambda: dataclasses.replace(uwb, ranges=()),
    }
    return odd[case]()


def _with(uwb: UwbRanges, r: AnchorRange) -> UwbRanges:
    return dataclasses.replace(uwb, ranges=(r, *uwb.ranges[1:]))


@pytest.mark.parametrize("case", ["not finite", "negative", "too long", "with a quality",
                                  "unknown anchor", "duplicate anchor", "an int range",
                                  "late", "new anchor set", "no ranges"])
def test_messages_it_does_not_take_are_declined_with_nothing_changed(
        case: str, tracking: tuple[Filter, list[Frame]]) -> None:
    """A range the gate or the resolver says anything about, a late message, anchors whose
    arrays are not made yet: None, and the filter as it was; the reference then takes it."""
    flt, frames = tracking
    step = flt.epoch_step
    assert step is not None
    uwb = _next_message(frames)
    before = state(flt)
    assert step(uwb) is not None or case == "new anchor set"  # (the common one is taken)
    before = state(flt)
    odd = _odd(uwb, case, flt)
    assert step(odd) is None
    assert state(flt) == before


def test_while_waiting_or_recording_it_declines() -> None:
    """Before the start and with records for the smoother, every message is the
    reference's."""
    sim = simulate(handheld_async(5))
    cfg = parse(simulation_toml(sim)).filter_config()
    waiting, recording = Filter(cfg), Filter(cfg, record=True)
    declined = {id(waiting): 0, id(recording): 0}
    for flt in (waiting, recording):
        step = flt.epoch_step
        assert step is not None
        for frame in list(merge(sim.imu, sim.uwb))[:6000]:
            if isinstance(frame, ImuSample):
                flt.predict(frame)
                continue
            if flt is recording or flt.ekf is None:
                assert step(frame) is None
                declined[id(flt)] += 1
            flt.update(frame)
    assert all(n > 100 for n in declined.values())
    assert recording.records


def test_no_step_without_the_core_or_when_loose() -> None:
    cfg = FilterConfig(anchors_m={0: (0.0, 0.0, 0.0)})
    assert Filter(dataclasses.replace(cfg, mode=cfg.mode.LOOSE)).epoch_step is None
    with native.pure_python():
        assert Filter(cfg).epoch_step is None


def test_the_ranges_kept_are_the_references(tracking: tuple[Filter, list[Frame]]) -> None:
    """RangeWindow's latest range of each anchor: the message's time, the anchor's position
    as a list of floats, the range as a float (what ``add`` keeps)."""
    flt, frames = tracking
    uwb = _next_message(frames)
    assert flt.epoch_step is not None and flt.epoch_step(uwb) is not None
    r = uwb.ranges[0]
    t, pos, rng = flt.ranges.latest[r.anchor_id]
    assert t == uwb.t_ns and rng == r.range_m and type(rng) is float
    assert pos == list(np.array(flt._configured[r.anchor_id], dtype=float).tolist())


@pytest.mark.parametrize("odd", ["P not contiguous", "a variance out of bounds",
                                 "odd anchor statistics", "a state not finite",
                                 "a position not a number"])
def test_the_rarer_branches_are_the_python_steps(odd: str) -> None:
    """Once running, each twin is given the same odd state: the C step hands the fuse (P in
    Fortran order; a NaN distance, which the C fuse declines), the clamp, the outcomes or
    the restart to the Python steps, and the twins stay the same to the bit."""
    sim = simulate(handheld_async(6))
    fast, slow, taken = twins(parse(simulation_toml(sim)).filter_config())
    frames = list(merge(sim.imu, sim.uwb))
    done = False
    for k, frame in enumerate(frames):
        if isinstance(frame, ImuSample):
            fast.predict(frame)
            slow.predict(frame)
            continue
        assert repr(fast.update(frame)) == repr(slow.update(frame)), f"message {k}"
        if not done and fast._aligned and k > len(frames) // 3:
            done = True
            for f in (fast, slow):
                assert f.ekf is not None
                if odd == "P not contiguous":
                    f.ekf.P = np.asfortranarray(f.ekf.P)
                elif odd == "a variance out of bounds":
                    f.ekf.P[9, 9] = 10.0  # a gyro bias: the ranges barely see it
                elif odd == "odd anchor statistics":
                    stats = f.anchor_stats[next(iter(f.anchor_stats))]
                    stats.rejected = 0.0  # type: ignore[assignment]
                elif odd == "a state not finite":
                    f.ekf.v[0] = math.inf
                else:
                    f.ekf.p[0] = math.nan
        if done and k % 40 == 0:
            assert state(fast) == state(slow), f"message {k}"
    assert done and state(fast) == state(slow)
    assert taken[0] > 1000  # (the common message the C step's, before and after)
    counters = fast.counters
    if odd == "a variance out of bounds":
        assert counters["covariance_clamped"] > 0
    if odd in ("a state not finite", "a position not a number"):
        assert counters["restarts"] > 0


@pytest.mark.parametrize("odd", ["an IMU gap", "inconsistent", "side unresolved",
                                 "coasting", "P not contiguous", "not finite", "waiting"])
def test_poses_it_does_not_make_are_the_references(odd: str) -> None:
    """A fault, a note, coasting, a state the reference restarts from, no filter: the C pose
    declines, and Filter.pose gives the reference's."""
    sim = simulate(handheld_async(4))
    fast, slow, _ = twins(parse(simulation_toml(sim)).filter_config())
    frames = list(merge(sim.imu, sim.uwb))
    for flt in (fast, slow):
        for frame in frames[: len(frames) // 2]:
            flt.predict(frame) if isinstance(frame, ImuSample) else flt.update(frame)
        assert flt.ekf is not None
        if flt is fast:  # (as it runs, the C core makes its poses)
            assert fast.pose_step is not None and isinstance(fast.pose_step(), Pose)
        if odd == "an IMU gap":
            flt.monitor.imu_gap = True
        elif odd == "inconsistent":
            flt.monitor._inconsistent_since_ns = flt.t_ns
        elif odd == "side unresolved":
            flt.monitor.mirror_unresolved = True
        elif odd == "coasting":
            flt.t_ns = (flt.t_ns or 0) + 3 * 10**9
        elif odd == "P not contiguous":
            flt.ekf.P = np.asfortranarray(flt.ekf.P)
        elif odd == "not finite":
            flt.ekf.p[0] = math.nan
        else:
            flt.ekf = None
    assert fast.pose_step is not None and fast.pose_step() is NotImplemented
    assert repr(fast.pose()) == repr(slow.pose())
    assert state(fast) == state(slow)


def test_known_anchors_of_any_container_are_pythons_in() -> None:
    """``known_anchors`` given as a tuple (it is tested with ``in``): taken alike."""
    sim = simulate(handheld_async(2))
    cfg = parse(simulation_toml(sim)).filter_config()
    cfg = dataclasses.replace(cfg, gating=dataclasses.replace(
        cfg.gating, known_anchors=tuple(sorted(cfg.anchors_m)[:-1])))  # type: ignore[arg-type]
    taken, declined, _ = run_both(cfg, list(merge(sim.imu, sim.uwb))[:12000],
                                  check_every=200)
    assert taken > 0 and declined > 0  # (the last anchor's ranges: rejected, Python's)


def test_a_side_flipped_by_the_fix_while_aligning_is_the_references() -> None:
    """While aligning, the message's fix may flip the mirror side (the ranges tell it): the
    C step hands the rest of the message to Python (a restart), the twins stay the same."""
    sim = simulate(handheld_async(3))
    fast, slow, taken = twins(parse(simulation_toml(sim)).filter_config())
    flipped: list[Filter] = []
    handed: list[bool] = []
    for k, frame in enumerate(merge(sim.imu, sim.uwb)):
        if isinstance(frame, ImuSample):
            fast.predict(frame)
            slow.predict(frame)
            continue
        if not flipped and fast.ekf is not None and not fast._aligned and taken[2] > 20:
            for flt in (fast, slow):  # the next fix flips the side, as weigh() would
                fix_once = flt.ranges.fix

                def flipping(*args: Any, flt: Filter = flt, fix: Any = fix_once,
                             **kwargs: Any) -> Any:
                    out = fix(*args, **kwargs)
                    flt.ranges.fix = fix  # type: ignore[method-assign]
                    flt.mirror.flipped = True
                    flipped.append(flt)
                    return out
                flt.ranges.fix = flipping  # type: ignore[method-assign]
        before = taken[0]
        assert repr(fast.update(frame)) == repr(slow.update(frame)), f"message {k}"
        if len(flipped) == 2 and not handed:
            handed.append(taken[0] == before + 1)  # the flipping message: the C step's
        assert repr(fast.pose()) == repr(slow.pose())
        if len(flipped) == 2 and k % 25 == 0:
            assert state(fast) == state(slow), f"message {k}"
        if len(flipped) == 2 and fast._aligned:
            break
    assert len(flipped) == 2 and fast.counters["restarts"] == slow.counters["restarts"] == 1
    assert handed == [True] and state(fast) == state(slow)


def test_the_epochs_transition_is_kept_for_the_smoother_only() -> None:
    """Φ over an epoch is multiplied up only where the smoother asks for it (``record``);
    asking an Eskf that does not keep it is a bug, said loudly."""
    sim = simulate(handheld_async(5))
    cfg = parse(simulation_toml(sim)).filter_config()
    plain, recording = Filter(cfg), Filter(cfg, record=True)
    for flt in (plain, recording):
        for frame in merge(sim.imu, sim.uwb):
            flt.predict(frame) if isinstance(frame, ImuSample) else flt.update(frame)
            if flt.ekf is not None:
                break
    assert plain.ekf is not None and recording.ekf is not None
    assert not plain.ekf.keep_transition and recording.ekf.keep_transition
    with pytest.raises(RuntimeError, match="keep_transition"):
        plain.ekf.take_epoch(with_phi=True)


def test_the_c_steps_propagate_the_covariance_themselves(monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    """Without Gauss–Markov states the C steps (IMU and UWB) propagate the covariance
    themselves, never through the method; with them, every propagation is the method's."""
    calls = [0]
    method = Eskf.propagate

    def counted(ekf: Eskf) -> None:
        calls[0] += 1
        method(ekf)

    monkeypatch.setattr(Eskf, "propagate", counted)
    sim = simulate(handheld_async(2))
    cfg = parse(simulation_toml(sim)).filter_config()
    frames = [f for f in merge(sim.imu, sim.uwb) if f.t_ns < sim.imu[0].t_ns + 20 * 10**9]
    made = []
    for multipath in (False, True):
        calls[0] = 0
        flt = Filter(dataclasses.replace(cfg, multipath_states=multipath))
        for frame in frames:
            flt.predict(frame) if isinstance(frame, ImuSample) else flt.update(frame)
        assert flt.ekf is not None and flt.ekf.interval_s < 0.05
        made.append(calls[0])
    assert made[0] == 0 and made[1] > 500


def test_while_recording_the_imu_steps_propagation_keeps_the_epochs_transition() -> None:
    """Recording for the smoother, the epoch step declines but the IMU step still propagates,
    multiplying up the epoch's Φ: the same as the reference's, to the bit."""
    sim = simulate(ceiling_room(2))
    cfg = parse(simulation_toml(sim)).filter_config()
    fast, slow = Filter(cfg, record=True), Filter(cfg, record=True)
    slow.epoch_step = slow.pose_step = slow.imu_step = None
    assert fast.imu_step is not None
    frames = [f for f in merge(sim.imu, sim.uwb) if f.t_ns < sim.imu[0].t_ns + 20 * 10**9]
    for k, frame in enumerate(frames):
        for flt in (fast, slow):
            flt.predict(frame) if isinstance(frame, ImuSample) else flt.update(frame)
        if k % 50 == 0:
            assert state(fast) == state(slow), f"frame {k}"
    assert fast.ekf is not None and fast.ekf.keep_transition
    assert state(fast) == state(slow)
