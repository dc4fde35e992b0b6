"""Estimator integrity: accuracy on unseen-style set-ups, and behaviour under sensor faults.

    python benchmarks/bench_integrity.py [--seeds 3] [--data ../shared/data] [--only NAME]

Accuracy (position RMSE against truth; real runs against truth with its motion-capture
glitches dropped): the tight filter with the log's own config (``uwbd simulate`` writes the
simulated sensors' specs; imported runs carry anchors, mounting and lever arm only) on

* ``seed_layout``: the default simulator run (6 anchors, 10 Hz epochs), first 8 s left out;
* ``ceiling_room``: 4 nearly coplanar anchors at 2.35-2.55 m, tag at 0.35-0.57 m, NLOS, one
  anchor out for 20 s, 0.27 m lever arm; first 8 s left out;
* ``handheld_async``: one range per message, 170 Hz round-robin over 8 anchors; 10 s out;
* the real flight ``iasl-s1`` and the real handheld run ``inrol-env1`` (first 10 s out),
  with UWB least squares beside it for reference; on ``inrol-env1`` also with the range
  model ``uwbd calibrate-ranges`` fits on ``inrol-calib`` (another room, same hardware;
  degrees 1 and 2 of the tag's term, the distance term, the anchors' delays and the
  noise's keys, delay states off, all as it writes them).

Faults on the seed layout: the IMU pinned at full scale for 0.5 s, one corrupted sample,
a 30 s IMU gap, a 20 s UWB outage, every anchor NLOS (+0.5-2 m each) for 10 s (3 seeds).
Printed per fault: exceptions, non-finite poses, the
largest error during and after it, how long after the data returned the error was back
under 0.3 m for good, whether the filter said "tracking" while more than 1 m off, how
often σ covered the error (|e_xy| ≤ 3 σ_xy) during the fault, and the largest heading
error 15-20 s after the data returned.

A wrong installation on the seed layout, per seed (the simulated ranges true, the config
wrong): anchor 3 surveyed 1 m off in height, 1 m off sideways, or its ranges +0.5 m long;
the lever arm 0.3 m off; a ground vehicle with NHC whose mounting is typed turned by 90°
about z. Printed: 3D RMSE, how many poses carried each installation fault, how often the
protection levels bounded the error (and their median), how many poses said healthy while
more than 0.5 m off, how often an anchor was excluded, and the anchors named at the end.
The real runs' rows say the same of theirs (both are taken as installed right).

Random installations (``--only campaign``, :mod:`uwbd.tools.campaign`): ``--cases`` (60)
seeded layouts, vehicles and faults, each run fault-free and with its fault; per fault kind
the poses beyond the protection levels, those healthy while beyond the alert limits, the
fault-free availability, how often the fault was detected and named, and the RMSE against
the fault-free run. Seeds 0.. are the set to tune on; ``--report`` runs the set from 1000.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.frames import UwbRanges
from uwbd.config import parse
from uwbd.config.overrides import to_toml, write_toml
from uwbd.fusion.settings import IDENTITY3, Z_DOWN, FilterConfig
from uwbd.fusion.types import Pose
from uwbd.tools.baselines import UwbLeastSquares
from uwbd.tools.campaign import (
    HORIZONTAL_ALERT_M,
    REPORT_SEEDS_FROM,
    VERTICAL_ALERT_M,
    WARM_UP_S,
    campaign,
)
from uwbd.tools.evaluate import merge, run_filter, run_method, score, truth_spikes
from uwbd.tools.importer import INROL_LEVER_ARM_M, INROL_MOUNTING, Dataset, load_iasl, load_inrol
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.range_calibration import calibrate, range_samples
from uwbd.tools.sim_presets import PRESETS
from uwbd.tools.simulator import SimConfig, Simulation, simulate

Vec3 = tuple[float, float, float]
Rotation = tuple[Vec3, Vec3, Vec3]
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NS = 1_000_000_000


def sim_config(sim: Simulation) -> FilterConfig:
    return parse(simulation_toml(sim)).filter_config()


def tracks(poses: list[Pose]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.array([p.t_ns for p in poses], dtype=np.int64)
    pos = np.array([p.position_m for p in poses]).reshape(-1, 3)
    cov = np.array([np.array(p.covariance).reshape(6, 6)[:3, :3] for p in poses]).reshape(-1, 3, 3)
    return t, pos, cov


def findings(poses: list[Pose], truth_t_ns: np.ndarray | None = None,
             truth_p_m: np.ndarray | None = None, skip_s: float = 0.0) -> str:
    """How often the window test said something, and (with truth) how often the protection
    levels bounded the error, their median, and the healthy poses more than 0.5 m off."""
    if truth_t_ns is not None:
        poses = [q for q in poses if q.t_ns >= truth_t_ns[0] + skip_s * NS]
    n = len(poses)
    said = {k: sum(k in q.health.faults or k in q.health.notes for q in poses)
            for k in ("anchor_inconsistent", "anchor_excluded", "lever_arm_inconsistent")}
    text = ", ".join(f"{k} {v}/{n}" for k, v in said.items())
    if truth_t_ns is None or truth_p_m is None or not n:
        return text
    t, p, _ = tracks(poses)
    e = p - np.column_stack([np.interp(t, truth_t_ns, truth_p_m[:, i]) for i in range(3)])
    hpl = np.array([np.nan if q.health.horizontal_protection_m is None
                    else q.health.horizontal_protection_m for q in poses])
    vpl = np.array([np.nan if q.health.vertical_protection_m is None
                    else q.health.vertical_protection_m for q in poses])
    healthy = np.array([q.health.healthy for q in poses])
    off = np.linalg.norm(e, axis=1) > 0.5
    known = np.isfinite(hpl) & np.isfinite(vpl)
    beyond = known & ((np.hypot(e[:, 0], e[:, 1]) > hpl) | (np.abs(e[:, 2]) > vpl))
    return (text + f"; error beyond the PL {beyond.mean():.2%} (PL unknown "
            f"{1 - known.mean():.1%}; median HPL {np.nanmedian(hpl):.2f} m, VPL "
            f"{np.nanmedian(vpl):.2f} m); healthy {healthy.mean():.0%}, "
            f"healthy while >0.5 m off {int((healthy & off).sum())}")


def row(name: str, acc: object, extra: str = "") -> None:
    a = acc
    print(f"  {name:<34} XY {a.rmse_xy_m:6.3f}  Z {a.rmse_z_m:6.3f}  3D {a.rmse_3d_m:6.3f}"  # type: ignore[attr-defined]
          f"  NEES/3 {a.nees_mean:6.2f}  {extra}")  # type: ignore[attr-defined]


def accuracy_sims(seeds: int, only: str | None) -> None:
    for name, preset in PRESETS.items():
        if only and only != name:
            continue
        skip = 10.0 if name == "handheld_async" else 8.0
        accs, lsq = [], []
        t0 = time.perf_counter()
        for seed in range(seeds):
            sim = simulate(preset(seed))
            cfg = sim_config(sim)
            poses, _, _ = run_filter(cfg, merge(sim.imu, sim.uwb))
            t, p, c = tracks(poses)
            accs.append(score(t, p, sim.truth_t_ns, sim.truth_p_m, c, skip))
            tl, pl = run_method(UwbLeastSquares(cfg), merge(sim.imu, sim.uwb))
            lsq.append(score(tl, pl, sim.truth_t_ns, sim.truth_p_m, None, skip))
        print(f"{name} ({seeds} seeds, {time.perf_counter() - t0:.1f} s)")
        for label, group in (("tight ESKF, datasheet config", accs), ("UWB least squares", lsq)):
            mean = type(group[0])(sum(a.n for a in group), *(
                float(np.mean([getattr(a, f) for a in group]))
                for f in ("rmse_xy_m", "rmse_z_m", "rmse_3d_m", "nees_mean")))
            row(label, mean, "per seed XY " + " ".join(f"{a.rmse_xy_m:.3f}" for a in group))


def accuracy_real(data: Path, only: str | None) -> None:
    loaders: dict[str, tuple[Callable[[Path], Dataset], Rotation, Vec3, float]] = {
        "iasl-s1": (load_iasl, Z_DOWN, (0.0, 0.0, 0.0), 0.0),
        "inrol-env1": (load_inrol, INROL_MOUNTING, INROL_LEVER_ARM_M, 10.0),
    }
    for name, (load, mounting, lever, skip) in loaders.items():
        if only and only != name:
            continue
        directory = data / name
        if not directory.is_dir():
            print(f"{name}: skipped ({directory} not found)")
            continue
        ds = load(directory)
        clean = ~truth_spikes(ds.truth_t_ns, ds.truth_p_m)
        tt, tp = ds.truth_t_ns[clean], ds.truth_p_m[clean]
        cfg = FilterConfig(anchors_m=ds.anchors_m, mounting_rotation=mounting,
                           lever_arm_m=lever)
        t0 = time.perf_counter()
        poses, _, flt = run_filter(cfg, merge(ds.imu, ds.uwb))
        elapsed = time.perf_counter() - t0
        t, p, c = tracks(poses)
        print(f"{name} (filter {elapsed:.1f} s)")
        row("tight ESKF, defaults", score(t, p, tt, tp, c, skip),
            f"restarts {flt.counters['restarts']}, resets {flt.counters['position_resets']}, "
            + findings(poses, tt, tp, skip))
        if name == "inrol-env1":
            for degree, anchor_degree in ((1, 0), (2, 0), (1, 1)):
                calibrated = calibrated_config(data / "inrol-calib", degree, ds, mounting,
                                               lever, anchor_degree)
                if calibrated is None:
                    print("  range model: skipped (inrol-calib not found)")
                    break
                t0 = time.perf_counter()
                poses, _, flt = run_filter(calibrated, merge(ds.imu, ds.uwb))
                t, p, c = tracks(poses)
                row(f"range model from inrol-calib, deg {degree}"
                    + (f", anchors' {anchor_degree}" if anchor_degree else ""),
                    score(t, p, tt, tp, c, skip),
                    f"filter {time.perf_counter() - t0:.1f} s, " + findings(poses, tt, tp, skip))
        tl, pl = run_method(UwbLeastSquares(cfg), merge(ds.imu, ds.uwb))
        row("UWB least squares", score(tl, pl, tt, tp, None, skip))


def calibrated_config(directory: Path, degree: int, scored: Dataset, mounting: Rotation,
                      lever_arm_m: Vec3, anchor_degree: int = 0) -> FilterConfig | None:
    """The config ``uwbd calibrate-ranges`` writes from the calibration recording (the tag's
    term of ``degree``, the anchors' of ``anchor_degree``, the distance term, the anchors'
    delays, the noise's keys), merged into the scored dataset's (its anchors with their
    orientations, as ``uwbd import`` writes them)."""
    if not directory.is_dir():
        return None
    ds = load_inrol(directory)
    samples = range_samples(ds.uwb, ds.anchors_m, ds.truth_t_ns, ds.truth_p_m,
                            ds.truth_rotation, ds.lever_arm_m, IDENTITY3, ds.anchor_axes)
    keys = calibrate(samples, degree, anchor_degree=anchor_degree).keys()
    text = (to_toml([], scored.anchors_m, mounting, lever_arm_m, fusion=keys.get("fusion"),
                    anchor_orientations_xyzw=scored.anchor_orientations_xyzw)
            + write_toml({"range_model": keys["range_model"]}))
    return parse(text, f"calibrate-ranges {directory}").filter_config()


def fault_case(name: str, cfg: SimConfig, start_s: float, end_s: float) -> None:
    sim = simulate(cfg)
    fcfg = sim_config(sim)
    try:
        poses, _, flt = run_filter(fcfg, merge(sim.imu, sim.uwb), pose_period_ns=NS // 10)
    except Exception:  # the point of the benchmark: report it, go on
        print(f"  {name:<26} EXCEPTION\n{traceback.format_exc()}")
        return
    t, p, c = tracks(poses)
    finite = np.isfinite(p).all(axis=1)
    t0 = sim.truth_t_ns[0]
    truth = np.column_stack([np.interp(t, sim.truth_t_ns, sim.truth_p_m[:, i]) for i in range(3)])
    err = np.linalg.norm(p[:, :2] - truth[:, :2], axis=1)
    s = (t - t0) / NS
    during = (s >= start_s) & (s < end_s)
    after = s >= end_s
    bad_after = np.flatnonzero(after & (err >= 0.3))
    back_s = (s[bad_after[-1]] - end_s) if len(bad_after) else 0.0
    sigma = np.sqrt(c[:, 0, 0] + c[:, 1, 1])
    covered = float(np.mean(err[during] <= 3 * sigma[during])) if during.any() else math.nan
    false_healthy = sum(1 for q, e in zip(poses, err, strict=True)
                        if e > 1.0 and q.health.healthy)
    yaw_truth = np.interp(t, sim.truth_t_ns, np.unwrap(sim.truth_yaw_rad))
    yaw = np.array([math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
                    for x, y, z, w in (q.orientation_xyzw for q in poses)])
    yaw_err = np.degrees(np.abs(np.angle(np.exp(1j * (yaw - yaw_truth)))))
    late = (s >= end_s + 15) & (s < end_s + 20)
    heading = f"{yaw_err[late].max():5.1f}" if late.any() else "  n/a"
    print(f"  {name:<26} non-finite {int((~finite).sum())}  max err during {err[during].max():6.2f}"
          f" m  max after {err[after].max():6.2f} m  under 0.3 m for good after {back_s:5.1f} s"
          f"  'tracking' while >1 m off: {false_healthy}  sigma covers {covered:4.0%}"
          f"  heading err 15-20 s after {heading} deg  restarts {flt.counters['restarts']}")


def faults() -> None:
    print("faults (seed layout, seed 0, datasheet config)")
    fault_case("IMU pinned 0.5 s", SimConfig(imu_saturations_s=((20.0, 0.5),)), 20.0, 20.5)
    fault_case("one corrupted sample", SimConfig(imu_spikes_s=(20.0,)), 20.0, 20.01)
    fault_case("IMU gap 30 s", SimConfig(imu_gaps_s=((12.0, 30.0),)), 12.0, 42.0)
    fault_case("UWB outage 20 s", SimConfig(uwb_outages_s=((15.0, 20.0),)), 15.0, 35.0)
    for seed in range(3):
        fault_case(f"all NLOS 10 s, seed {seed}",
                   SimConfig(seed=seed, nlos_all_s=((30.0, 10.0),)), 30.0, 40.0)


INSTALLATION_FAULTS = ("none", "1 m up", "1 m sideways", "+0.5 m ranges", "lever arm +0.3 m",
                       "mounting 90 deg about z")


def wrong_installation(seeds: int) -> None:
    print("wrong installation (seed layout, anchor 3; the mounting case a ground vehicle with "
          "NHC; the first 8 s left out)")
    for fault in INSTALLATION_FAULTS:
        for seed in range(seeds):
            sim = simulate(SimConfig(seed=seed, ground_vehicle="mounting" in fault))
            cfg = sim_config(sim)
            anchors = {a: list(pos) for a, pos in cfg.anchors_m.items()}
            anchors[3][2 if fault == "1 m up" else 0] += 1.0 if "1 m" in fault else 0.0
            cfg = dataclasses.replace(cfg, anchors_m={a: (x, y, z) for a, (x, y, z)
                                                      in anchors.items()})
            if fault.startswith("lever"):
                x, y, z = cfg.lever_arm_m
                cfg = dataclasses.replace(cfg, lever_arm_m=(x + 0.3, y, z))
            if fault.startswith("mounting"):
                turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
                rows = (turn @ np.array(cfg.mounting_rotation)).tolist()
                cfg = dataclasses.replace(cfg, nhc=True, mounting_rotation=(
                    (rows[0][0], rows[0][1], rows[0][2]), (rows[1][0], rows[1][1], rows[1][2]),
                    (rows[2][0], rows[2][1], rows[2][2])))
            uwb = sim.uwb if fault != "+0.5 m ranges" else [dataclasses.replace(
                e, ranges=tuple(dataclasses.replace(r, range_m=r.range_m + 0.5)
                                if r.anchor_id == 3 else r for r in e.ranges))
                for e in sim.uwb if isinstance(e, UwbRanges)]
            poses, _, flt = run_filter(cfg, merge(sim.imu, uwb))
            poses = [q for q in poses if q.t_ns >= sim.truth_t_ns[0] + 8 * NS]
            t, p, _ = tracks(poses)
            truth = np.column_stack([np.interp(t, sim.truth_t_ns, sim.truth_p_m[:, i])
                                     for i in range(3)])
            err = np.linalg.norm(p - truth, axis=1)
            mounting = sum("mounting_inconsistent" in q.health.faults for q in poses)
            print(f"  {fault:<23} seed {seed}  3D RMSE {math.sqrt(np.mean(err ** 2)):6.3f}  "
                  f"{findings(poses, sim.truth_t_ns, sim.truth_p_m)}, mounting_inconsistent "
                  f"{mounting}/{len(poses)}; anchors excluded "
                  f"{flt.counters['anchors_excluded']}x (named at the end: "
                  f"{sorted(flt.findings.consistency.findings) or 'none'})")


def random_installations(cases: int, report: bool) -> None:
    """The campaign of :mod:`uwbd.tools.campaign`, one line per fault kind."""
    first = REPORT_SEEDS_FROM if report else 0
    t0 = time.perf_counter()
    rows = campaign(range(first, first + cases), workers=os.cpu_count() or 1)
    print(f"random installations: seeds {first}..{first + cases - 1} ("
          f"{'report' if report else 'tuning'} set), each fault-free and with its fault; "
          f"poses after the first {WARM_UP_S:.0f} s; alert limits {HORIZONTAL_ALERT_M} m h, "
          f"{VERTICAL_ALERT_M} m v; {time.perf_counter() - t0:.0f} s")
    print(f"  {'fault':<16} {'cases':>5} {'>PL faulty':>10} {'>PL free':>9} "
          f"{'healthy>AL faulty':>17} {'free':>5} {'avail free':>10} {'redundant':>9} "
          f"{'faulty':>6} "
          f"{'detected':>8} "
          f"{'false alarm':>11} {'named':>6} {'RMSE x med':>10} {'max':>6}")
    for r in rows:
        print(f"  {r.kind:<16} {r.cases:>5} {r.beyond_pl:>10.1%} {r.free_beyond_pl:>9.1%} "
              f"{r.healthy_beyond_alert:>17} {r.free_healthy_beyond_alert:>5} "
              f"{r.availability:>10.1%} {r.availability_redundant:>9.1%} "
              f"{r.availability_faulty:>6.1%} "
              f"{r.detected:>8.0%} {r.false_alarm:>11.0%} "
              f"{r.named:>6.0%} {r.rmse_ratio_median:>10.2f} {r.rmse_ratio_max:>6.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--only", help="one case: a preset, a dataset, 'faults', 'installation' "
                    "or 'campaign'")
    ap.add_argument("--cases", type=int, default=60, help="random installations (campaign)")
    ap.add_argument("--report", action="store_true",
                    help="the campaign's report seeds (from 1000), not its tuning seeds")
    args = ap.parse_args()
    if args.only == "campaign":
        random_installations(args.cases, args.report)
        return
    accuracy_sims(args.seeds, args.only)
    accuracy_real(args.data, args.only)
    if args.only in (None, "faults"):
        faults()
    if args.only in (None, "installation"):
        wrong_installation(args.seeds)
    if args.only is None:
        random_installations(args.cases, args.report)


if __name__ == "__main__":
    main()
