"""``uwbd survey`` on simulated runs: how far it brings tape-measured anchors to the truth.

    python benchmarks/bench_survey.py [--seeds 3] [--perturb 0.1 0.15 0.2] [--only NAME]
                                      [--sources tag pairs tag+pairs] [--no-fusion]

Layouts: ``seed_layout`` (the default run: 6 anchors over 25 x 60 m, 4 on the ground and 2
at 5 m, 10 Hz epochs, 58 s), ``ceiling_room`` (4 nearly coplanar anchors at 2.35-2.55 m,
a ground robot below, one anchor out for 20 s, 76 s) and ``handheld_async`` (8 anchors at
0.3 and 2.3 m around a 6 x 5 m room, carried at 1.1 m, one range a message, NLOS on the
low anchors 5 times as often; 59 s). Each run is written as a log
(``write_simulation``) and read back: the tag's ranges are what the log holds.

The config's anchors are the true ones moved by ``--perturb`` m each, in a random 3-D
direction (one draw per seed). The simulator has no anchor-to-anchor ranging, so those are
made here: every pair once a second over the run, the true distance plus white noise of
σ 0.05 m (``pairs``: all pairs; ``ma``: the TREK1000's three, A0-A1, A0-A2, A1-A2).

Sources surveyed: ``tag`` (the log alone), ``pairs`` (anchor-to-anchor ranges alone),
``tag+pairs``, ``tag+ma`` (ceiling room). Gauges: ``config`` (every anchor tied to its
configured position, σ 0.2 m: the config's frame), ``user`` (``--origin``/``--x-axis``/
``--y-side``: seed layout 1, 5, 0; the rooms 0, 1, 3; each pair lies along +x, so the
user's frame is the simulator's shifted) and ``user+h`` (the same with every anchor's
height measured, ``--height``: the true height + N(0, 0.01 m), in "before" too). Errors
are measured in the frame the output is in: the config's frame is the simulator's (so the
part of the tape error that moves the whole layout, which no range can see, stays in the
"after"); the user's frame is the one the true anchors define (truth carried into it;
"before" is the perturbed config carried into it the same way, i.e. as the user would
have tape-measured it in that frame).

Printed per layout, source, gauge and perturbation, averaged over seeds: the anchors' RMS
3-D error before and after (and horizontal, vertical), its ratio, the RMS of error/σ (1
when the reported σ is right), the tight filter's XY RMSE (``run_filter`` on the log's
frames, first 8 s left out) with the true, the perturbed and the surveyed anchors, and the
survey's run time.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.frames import AnchorPair, AnchorRanges, Frame, UwbRanges
from uwbd.fusion.settings import FilterConfig
from uwbd.logs.reading import read_log
from uwbd.tools.evaluate import run_filter, score_poses
from uwbd.tools.logtools import load_recording, write_simulation
from uwbd.tools.sim_presets import PRESETS
from uwbd.tools.simulator import Simulation, simulate
from uwbd.tools.survey import Gauge, Settings, Survey, log_ranges, survey

Array = np.ndarray
GAUGES = {"seed_layout": (1, 5, 0), "ceiling_room": (0, 1, 3), "handheld_async": (0, 1, 3)}
PAIR_NOISE_M = 0.05
PAIR_PERIOD_S = 1.0
SKIP_S = 8.0
HEIGHT_NOISE_M = 0.01


def anchor_pairs(anchors: Array, t0_ns: int, t1_ns: int, which: str, seed: int
                 ) -> list[AnchorRanges]:
    """Anchor-to-anchor reports once a second: true distance + N(0, 0.05 m)."""
    rng = np.random.default_rng(7000 + seed)
    n = len(anchors)
    pairs = ([(0, 1), (0, 2), (1, 2)] if which == "ma"
             else [(a, b) for a in range(n) for b in range(a + 1, n)])
    out = []
    for t in range(t0_ns, t1_ns, int(PAIR_PERIOD_S * 1e9)):
        out.append(AnchorRanges(t, tuple(
            AnchorPair(a, b, float(np.linalg.norm(anchors[a] - anchors[b])
                                   + rng.normal(0, PAIR_NOISE_M)))
            for a, b in pairs)))
    return out


def perturb(anchors: Array, magnitude: float, seed: int) -> Array:
    rng = np.random.default_rng(100 + seed)
    d = rng.normal(size=anchors.shape)
    return np.asarray(anchors + d / np.linalg.norm(d, axis=1, keepdims=True) * magnitude)


def gauge_frame(anchors: Array, origin: int, x_axis: int) -> tuple[Array, Array]:
    """p' = R (p - t): ``origin`` to (0, 0, z), ``x_axis`` onto +x (as the survey does)."""
    o, x = anchors[origin], anchors[x_axis]
    heading = math.atan2(x[1] - o[1], x[0] - o[0])
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([o[0], o[1], 0.0])


@dataclass
class Run:
    sim: Simulation
    frames: list[Frame]
    uwb: list[UwbRanges]
    base: FilterConfig
    truth_t: Array
    truth_p: Array


def load_run(name: str, seed: int, folder: Path) -> Run:
    sim = simulate(PRESETS[name](seed))
    path = folder / f"{name}-{seed}.mcap"
    write_simulation(sim, path)
    contents = read_log(path)
    rec = load_recording(contents, str(path))
    uwb, _ = log_ranges(contents)
    return Run(sim, rec.frames, uwb, rec.config.filter_config(), rec.truth_t_ns, rec.truth_p_m)


def fusion_xy(run: Run, anchors: Array, R: Array, t: Array) -> float:
    """The tight filter's XY RMSE with ``anchors`` (in the frame p' = R (p - t))."""
    cfg = dataclasses.replace(run.base, anchors_m={i: (float(p[0]), float(p[1]), float(p[2]))
                                                   for i, p in enumerate(anchors)})
    poses, _, _ = run_filter(cfg, run.frames)
    truth = (run.truth_p - t) @ R.T
    return score_poses(poses, run.truth_t, truth, SKIP_S).rmse_xy_m


def errors(est: Array, true: Array) -> tuple[float, float, float]:
    e = est - true
    return (float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
            float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1)))),
            float(np.sqrt(np.mean(e[:, 2] ** 2))))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--perturb", type=float, nargs="+", default=[0.1, 0.15, 0.2])
    ap.add_argument("--only", choices=list(GAUGES))
    ap.add_argument("--sources", nargs="+", default=["tag", "pairs", "tag+pairs", "tag+ma"])
    ap.add_argument("--gauges", nargs="+", default=["config", "user", "user+h"])
    ap.add_argument("--offsets", action="store_true", help="survey with --range-offsets")
    ap.add_argument("--no-fusion", action="store_true", help="anchor errors only")
    args = ap.parse_args(argv)
    layouts = [args.only] if args.only else list(GAUGES)
    head = (f"{'layout':<15}{'source':<10}{'gauge':<7}{'pert':>5} | {'anchor 3-D m':>14} "
            f"{'ratio':>6} {'xy after':>8} {'z after':>8} {'e/σ':>5} | "
            f"{'fusion XY m: true':>17} {'pert':>6} {'surv':>6} {'s/t':>6} | {'s':>5}")
    print(head)
    print("-" * len(head))
    with tempfile.TemporaryDirectory(prefix="bench-survey-") as tmp:
        for name in layouts:
            runs = [load_run(name, seed, Path(tmp)) for seed in range(args.seeds)]
            true = np.array(runs[0].sim.config.anchors_m)
            o, x, y = GAUGES[name]
            R_true, t_true = gauge_frame(true, o, x)
            fusion_true: dict[tuple[str, int], float] = {}
            if not args.no_fusion:
                for gauge in args.gauges:
                    R, t = ((R_true, t_true) if gauge.startswith("user")
                            else (np.eye(3), np.zeros(3)))
                    for seed, run in enumerate(runs):
                        fusion_true[(gauge, seed)] = fusion_xy(run, (true - t) @ R.T, R, t)
            for source in args.sources:
                if name != "ceiling_room" and source == "tag+ma":
                    continue  # a TREK1000 network: 4 anchors, the ceiling room
                for gauge in args.gauges:
                    for magnitude in args.perturb:
                        rows = []
                        for seed, run in enumerate(runs):
                            rows.append(one(run, name, source, gauge, magnitude, seed, true,
                                            (o, x, y), args, fusion_true))
                        m = np.nanmean(np.array(rows), axis=0)
                        print(f"{name:<15}{source:<10}{gauge:<7}{magnitude:5.2f} | "
                              f"{m[0]:6.3f}->{m[1]:6.3f} {m[0] / m[1]:5.1f}x {m[2]:8.3f} "
                              f"{m[3]:8.3f} {m[4]:5.2f} | {m[5]:17.3f} {m[6]:6.3f} "
                              f"{m[7]:6.3f} {m[7] / m[5]:6.2f} | {m[8]:5.2f}", flush=True)
    return 0


def one(run: Run, name: str, source: str, gauge: str, magnitude: float, seed: int,
        true: Array, ids: tuple[int, int, int], args: argparse.Namespace,
        fusion_true: dict[tuple[str, int], float]) -> list[float]:
    o, x, y = ids
    tape = perturb(true, magnitude, seed)
    t0, t1 = run.uwb[0].t_ns, run.uwb[-1].t_ns
    pairs = (anchor_pairs(true, t0, t1, "ma" if source.endswith("ma") else "all", seed)
             if "pairs" in source or source.endswith("ma") else [])
    uwb = run.uwb if source.startswith("tag") else []
    user = gauge.startswith("user")
    heights: dict[int, float] = {}
    if gauge == "user+h":  # every height measured (a laser from the floor): σ 1 cm
        rng = np.random.default_rng(900 + seed)
        heights = {i: float(z + rng.normal(0, HEIGHT_NOISE_M)) for i, z in enumerate(true[:, 2])}
        tape = tape.copy()
        tape[:, 2] = [heights[i] for i in range(len(tape))]
    settings = Settings(gauge=Gauge(o, x, y) if user else Gauge(), heights_m=heights,
                        range_sigma_m=run.base.range_sigma_m, range_offsets=args.offsets,
                        offset_sigma_m=run.base.range_bias_sigma_m)
    began = time.perf_counter()
    result: Survey = survey({i: tuple(p) for i, p in enumerate(tape)}, uwb, pairs, settings)
    seconds = time.perf_counter() - began
    if user:
        R, t = gauge_frame(true, o, x)
        Rp, tp = gauge_frame(tape, o, x)
        truth_a, before = (true - t) @ R.T, (tape - tp) @ Rp.T
    else:
        R, t = np.eye(3), np.zeros(3)
        truth_a, before = true, tape
    after = np.array([result.anchors[i].position_m for i in range(len(true))])
    sigma = np.array([result.anchors[i].sigma_m for i in range(len(true))])
    e0 = errors(before, truth_a)[0]
    e1, e1_xy, e1_z = errors(after, truth_a)
    held = sigma > 0
    ratio = float(np.sqrt(np.mean(((after - truth_a)[held] / sigma[held]) ** 2)))
    if args.no_fusion:
        fus = [math.nan, math.nan, math.nan]
    else:
        fus = [fusion_true[(gauge, seed)], fusion_xy(run, before, R, t),
               fusion_xy(run, after, R, t)]
    return [e0, e1, e1_xy, e1_z, ratio, *fus, seconds]


if __name__ == "__main__":
    raise SystemExit(main())
