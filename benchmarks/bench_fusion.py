"""Fusion speed and accuracy, side by side in one run.

    python benchmarks/bench_fusion.py [--seeds 6] [--data ../shared/data/iasl-s1] [--speed-only]

Speed: the filter alone (frames built beforehand and frozen out of the garbage collector's
walks, as ``uwbd replay`` freezes its log) on a 200 Hz IMU and 8 anchors at 10 Hz,
per mode, and on a 100 Hz IMU with 170 single ranges a second (tight), driven as the daemon
drives it (``run_reads``: the IMU in reads of a pose period's samples, poses at 50 Hz, after
every epoch of several ranges, after a single range when one is due), as a multiple of real
time, on the C core and on the pure-Python reference;
and the cost of the range model (``[range_model]``, degrees 1 and 2 with anchor delays and
the distance term) against none on the single ranges.
Accuracy: position RMSE against ground truth for the baselines (pure INS, UWB least
squares, the same with static-point filtering at rest, the thesis's 4-state KF with its
dual-gain complementary attitude filter and static points, and that KF with the two gains
swapped; ``uwbd.tools.baselines.comparison_methods``) and the loose and
tight error-state filters (generic defaults; on the simulator also tight with the config
``uwbd simulate`` writes, which holds the simulated sensors' specs), on simulator runs
(mean over seeds; the first 8 s, the still start, left out) and on the real flight, scored
against all truth samples and against the truth with its motion-capture spikes removed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import math
import time
from pathlib import Path

import numpy as np

from drivers.frames import Frame, ImuSample, UwbRanges
from uwbd.config import parse
from uwbd.fusion.core import native
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.filter import Filter
from uwbd.fusion.models.range_model import RangeModel, n_coefficients
from uwbd.fusion.settings import Z_DOWN, FilterConfig, Mode
from uwbd.tools.baselines import comparison_methods
from uwbd.tools.evaluate import (
    HEADER,
    Accuracy,
    Times,
    merge,
    run_filter,
    run_method,
    run_smoother,
    score,
    score_poses,
    truth_spikes,
)
from uwbd.tools.importer import load_iasl
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.sim_presets import handheld_async
from uwbd.tools.simulator import SimConfig, Simulation, simulate

ANCHORS_8 = ((-5.0, 30.0, 0.0), (-5.0, -30.0, 0.0), (10.0, 10.0, 5.0), (10.0, -10.0, 5.0),
             (20.0, 30.0, 0.0), (20.0, -30.0, 0.0), (0.0, 0.0, 3.0), (15.0, 0.0, 3.0))
POSE_PERIOD_NS = 20_000_000  # poses at 50 Hz, as the daemon's default pose_rate_hz
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "iasl-s1"


def baselines(cfg: FilterConfig, imu: list[ImuSample], uwb: list[UwbRanges]
              ) -> dict[str, tuple[Times, Array]]:
    """Positions of the comparison methods over one recording."""
    return {name: run_method(m, merge(imu, uwb))
            for name, m in comparison_methods(cfg).items()}


def speed(modes: list[Mode]) -> None:
    """The filter alone, on the C core and on the pure-Python reference, side by side."""
    sim = simulate(SimConfig(anchors_m=ANCHORS_8, seed=1))
    loads = [(f"{mode.value}, 200 Hz IMU + 8 anchors x 10 Hz",
              FilterConfig(mode=mode, anchors_m=dict(enumerate(ANCHORS_8)),
                           mounting_rotation=Z_DOWN, lever_arm_m=sim.config.lever_arm_m),
              sim) for mode in modes]
    hand = simulate(handheld_async(1))
    loads.append(("tight, 100 Hz IMU + 170 single ranges/s",
                  parse(simulation_toml(hand)).filter_config(), hand))
    print("speed: the filter alone, as a multiple of real time (best of 3, the two "
          "implementations alternated: this VM's speed drifts within minutes)")
    for label, cfg, run in loads:
        frames = list(merge(run.imu, run.uwb))
        # the input, made beforehand, out of the collector's walks (as `uwbd replay` does
        # with its log): else each full collection walks every frame of the run
        gc.freeze()
        duration_s = (run.truth_t_ns[-1] - run.truth_t_ns[0]) / 1e9
        best = {"C core": math.inf, "pure Python": math.inf}
        for _ in range(3):
            for impl in ("C core", "pure Python"):
                with native.pure_python() if impl == "pure Python" else \
                        contextlib.nullcontext():
                    best[impl] = min(best[impl], _timed(cfg, frames))
        print(f"  {label}: C core {duration_s / best['C core']:5.0f} x, pure Python "
              f"{duration_s / best['pure Python']:5.0f} x (C core / pure Python "
              f"{best['pure Python'] / best['C core']:.2f}; "
              f"{best['C core'] / len(run.imu) * 1e6:.1f} us per IMU sample, all in)")


def range_model_cost() -> None:
    """The filter with the range model on (degree 1: a phase centre; degree 2: the rest
    taken off the ranges each epoch; both with the anchors' delays and the distance term,
    as ``calibrate-ranges`` writes them) and off, side by side, on single ranges at 170/s."""
    hand = simulate(handheld_async(1))
    base = parse(simulation_toml(hand)).filter_config()
    c2 = (0.003, 0.081, 0.029, -0.011, -0.009, 0.018, 0.010, 0.001)
    k, delays = 0.12, {a: 0.01 * a for a in range(len(hand.config.anchors_m))}
    loads = {"off": base, **{
        f"degree {d} + anchor delays + distance term": dataclasses.replace(
            base, range_model=RangeModel(d, c2[:n_coefficients(d)],
                                         anchor_delays_m=tuple(delays.items()),
                                         log_distance_m=k)) for d in (1, 2)}}
    # the model's runs on ranges that carry its delays and distance term (a filter whose
    # model the ranges contradict does other work: its checks' fixes, fading)
    carrying = [dataclasses.replace(f, ranges=tuple(dataclasses.replace(
        r, range_m=r.range_m + delays[r.anchor_id] + k * math.log(r.range_m))
        for r in f.ranges)) for f in hand.uwb]
    frames = {name: list(merge(hand.imu, hand.uwb if name == "off" else carrying))
              for name in loads}
    gc.freeze()
    best = dict.fromkeys(loads, math.inf)
    for _ in range(3):
        for name, cfg in loads.items():
            best[name] = min(best[name], _timed(cfg, frames[name]))
    print("range model: the filter alone, C core, 100 Hz IMU + 170 single ranges/s (best of 3, "
          "alternated)")
    for name, t in best.items():
        print(f"  {name}: {t:.2f} s ({100 * (t / best['off'] - 1):+.0f} % of off)")


def _timed(cfg: FilterConfig, frames: list[Frame]) -> float:
    t0 = time.perf_counter()
    run_reads(cfg, frames)
    return time.perf_counter() - t0


def run_reads(cfg: FilterConfig, frames: list[Frame]) -> int:
    """The filter as the daemon drives it: the IMU's samples in reads of a pose period's
    (what a batched port returns: ``Filter.predict_many``; never across a UWB message),
    poses at 50 Hz (at the end of the read a pose falls due in, the next due a period after
    that sample), after every epoch of several ranges, after a single range when due.
    Returns the poses made."""
    flt = Filter(cfg)
    due_ns, poses = -(2**63), 0
    read: list[ImuSample] = []
    per_read, first_ns = 0, None
    for frame in frames:
        if isinstance(frame, ImuSample):
            if not per_read:  # the IMU's rate from its first two samples (one a read till then)
                if first_ns is not None:
                    per_read = max(1, POSE_PERIOD_NS // max(frame.t_ns - first_ns, 1))
                first_ns = frame.t_ns
            read.append(frame)
            if len(read) < per_read:
                continue
        if read:
            flt.predict_many(read)
            due = next((s.t_ns for s in read if s.t_ns >= due_ns), None)
            read = []
            if due is not None and flt.pose() is not None:
                due_ns, poses = due + POSE_PERIOD_NS, poses + 1
        if isinstance(frame, UwbRanges):
            flt.update(frame)
            if (len(frame.ranges) >= 2 or frame.t_ns >= due_ns) and flt.pose() is not None:
                due_ns, poses = frame.t_ns + POSE_PERIOD_NS, poses + 1
    return poses


def accuracy_sim(seeds: int) -> None:
    rows: dict[str, list[Accuracy]] = {}
    for seed in range(seeds):
        sim: Simulation = simulate(SimConfig(seed=seed))
        anchors = dict(enumerate(sim.config.anchors_m))
        base = FilterConfig(anchors_m=anchors, mounting_rotation=Z_DOWN,
                            lever_arm_m=sim.config.lever_arm_m)
        for name, (t, p) in baselines(base, sim.imu, sim.uwb).items():
            rows.setdefault(name, []).append(score(t, p, sim.truth_t_ns, sim.truth_p_m, skip_s=8))
        # generic defaults, and the config `uwbd simulate` writes: the sensors' own specs
        configs = {f"{mode.value} ESKF": FilterConfig(
            mode=mode, anchors_m=anchors, mounting_rotation=Z_DOWN,
            lever_arm_m=sim.config.lever_arm_m) for mode in Mode}
        configs["tight, sensor specs"] = parse(simulation_toml(sim)).filter_config()
        for name, cfg in configs.items():
            poses, _, _ = run_filter(cfg, merge(sim.imu, sim.uwb))
            rows.setdefault(name, []).append(
                score_poses(poses, sim.truth_t_ns, sim.truth_p_m, skip_s=8))
        t, p, cov = run_smoother(configs["tight ESKF"], merge(sim.imu, sim.uwb))
        rows.setdefault("tight + RTS smoother", []).append(
            score(t, p, sim.truth_t_ns, sim.truth_p_m, cov, skip_s=8))
    print(f"\naccuracy: simulator, 6 anchors, sigma_range 0.10 m, mean of {seeds} seeds")
    print(HEADER)
    for name, accs in rows.items():
        mean = Accuracy(sum(a.n for a in accs), *(float(np.mean([getattr(a, f) for a in accs]))
                        for f in ("rmse_xy_m", "rmse_z_m", "rmse_3d_m", "nees_mean")))
        print(mean.row(name))


def accuracy_real(directory: Path) -> None:
    if not directory.is_dir():
        print(f"\n(real flight skipped: {directory} not found)")
        return
    ds = load_iasl(directory)
    clean = ~truth_spikes(ds.truth_t_ns, ds.truth_p_m)
    results: dict[str, tuple[Times, Array, Array | None]] = {}
    base = FilterConfig(anchors_m=ds.anchors_m, mounting_rotation=Z_DOWN)
    for name, (t, p) in baselines(base, ds.imu, ds.uwb).items():
        results[name] = (t, p, None)
    tag = [(e.t_ns, e.tag_position_m) for e in ds.uwb if e.tag_position_m is not None]
    results["tag's own solution"] = (np.array([x for x, _ in tag], dtype=np.int64),
                                     np.array([y for _, y in tag]), None)
    for mode in Mode:
        cfg = FilterConfig(mode=mode, anchors_m=ds.anchors_m, mounting_rotation=Z_DOWN)
        poses, _, _ = run_filter(cfg, merge(ds.imu, ds.uwb))
        results[f"{mode.value} ESKF"] = (
            np.array([q.t_ns for q in poses], dtype=np.int64),
            np.array([q.position_m for q in poses]),
            np.array([np.array(q.covariance).reshape(6, 6)[:3, :3] for q in poses]))
    results["tight + RTS smoother"] = run_smoother(
        FilterConfig(anchors_m=ds.anchors_m, mounting_rotation=Z_DOWN), merge(ds.imu, ds.uwb))
    for label, mask in (("all truth samples", np.ones_like(clean)),
                        (f"truth without its {int((~clean).sum())} mocap spike(s)", clean)):
        print(f"\naccuracy: real flight {directory.name}, {label}")
        print(HEADER)
        for name, (t, p, cov) in results.items():
            print(score(t, p, ds.truth_t_ns[mask], ds.truth_p_m[mask], cov).row(name))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--speed-only", action="store_true", help="skip the accuracy tables")
    args = ap.parse_args()
    speed(list(Mode))
    range_model_cost()
    if args.speed_only:
        return
    accuracy_sim(args.seeds)
    accuracy_real(args.data)


if __name__ == "__main__":
    main()
