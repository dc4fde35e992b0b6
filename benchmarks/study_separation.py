"""A study for the integrity issue (#43): would solution separation bound the error on random
installations? Offline, before the bank of sub-filters is built into the core.

    python benchmarks/study_separation.py [--cases 20] [--report]

For each campaign case (:mod:`uwbd.tools.campaign`), fault-free and with its fault, the
filter runs as it is (the main filter) and once more per anchor with that anchor's ranges
left out (the sub-filters: independent filters here, so their own decisions may differ from
the main one's; the bank will share them). At each main pose, with the sub-filters' poses
at the same time, in the position domain (Brenner 1996; the ARAIM algorithm description):

* the separation ``Δ_k = x_k − x_0`` and its covariance ``P_k − P_0`` (horizontal: the
  major axis; vertical: z), the threshold ``T_k = K_fa σ_Δk``, ``K_fa`` at a false-alert
  probability of 1e-4 shared over the anchors;
* the protection level ``max(K_md σ_0, max_k (T_k + K_md σ_k))``, ``K_md`` at the
  integrity risk 1e-3 shared over the hypotheses (the fault-free and one per anchor);
* detection: a separation over its threshold; the anchor named: the largest ``|Δ_k| / T_k``.

Printed per fault kind, beside the filter's own figures (campaign.score): the poses whose
error exceeds the SS protection level, the SS level's median against the filter's, how
often a faulty run was detected (and a fault-free one alarmed), and how often the faulty
anchor was named.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from statistics import NormalDist

import numpy as np

from drivers.frames import UwbRanges
from uwbd.fusion.types import Pose
from uwbd.tools.campaign import (
    FAULTS,
    NS,
    REPORT_SEEDS_FROM,
    WARM_UP_S,
    Case,
    draw_case,
    ranges_of,
    told,
)
from uwbd.tools.evaluate import merge, run_filter
from uwbd.tools.simulator import simulate

P_FA, RISK = 1e-4, 1e-3


def _cov3(pose: Pose) -> np.ndarray:
    return np.array(pose.covariance).reshape(6, 6)[:3, :3]


def _major(c: np.ndarray) -> float:
    return math.sqrt(max(float(np.linalg.eigvalsh(c[:2, :2])[-1]), 0.0))


def _without(messages: list[UwbRanges], anchor: int) -> list[UwbRanges]:
    return [dataclasses.replace(m, ranges=tuple(r for r in m.ranges if r.anchor_id != anchor))
            for m in messages]


def run(case: Case, faulty: bool) -> dict[str, float]:
    """One case, fault-free or faulty: the SS figures over its poses after the warm-up."""
    sim = simulate(case.sim)
    cfg = told(case, sim, faulty)
    uwb = ranges_of(case, sim, faulty)
    main, _, _ = run_filter(cfg, merge(sim.imu, uwb), pose_period_ns=NS // 10)
    anchors = sorted(cfg.anchors_m)
    subs = {}
    for a in anchors:
        poses, _, _ = run_filter(cfg, merge(sim.imu, _without(uwb, a)), pose_period_ns=NS // 10)
        subs[a] = {p.t_ns: p for p in poses}
    n = len(anchors)
    k_fa = NormalDist().inv_cdf(1 - P_FA / (2 * n))
    k_md = NormalDist().inv_cdf(1 - RISK / (2 * (n + 1)))
    t0 = sim.truth_t_ns[0] + WARM_UP_S * NS
    beyond = alarmed = poses_n = 0
    ss_hpl, own_hpl, votes = [], [], {a: 0.0 for a in anchors}
    for p in main:
        if p.t_ns < t0 or any(p.t_ns not in s for s in subs.values()):
            continue
        truth = np.array([np.interp(p.t_ns, sim.truth_t_ns, sim.truth_p_m[:, i])
                          for i in range(3)])
        c0 = _cov3(p)
        x0 = np.array(p.position_m)
        hpl, vpl = k_md * _major(c0), k_md * math.sqrt(max(c0[2, 2], 0.0))
        worst, worst_a, alarm = 0.0, None, False
        for a, s in subs.items():
            q = s[p.t_ns]
            ck, dx = _cov3(q), np.array(q.position_m) - x0
            dc = ck - c0
            sh, sv = max(_major(dc), 1e-3), math.sqrt(max(dc[2, 2], 1e-6))
            th, tv = k_fa * sh, k_fa * sv
            hpl = max(hpl, th + k_md * _major(ck))
            vpl = max(vpl, tv + k_md * math.sqrt(max(ck[2, 2], 0.0)))
            ratio = max(math.hypot(dx[0], dx[1]) / th, abs(dx[2]) / tv)
            alarm |= ratio > 1.0
            if ratio > worst:
                worst, worst_a = ratio, a
        if alarm and worst_a is not None:
            votes[worst_a] += 1
        alarmed += alarm
        poses_n += 1
        err = x0 - truth
        beyond += math.hypot(err[0], err[1]) > hpl or abs(err[2]) > vpl
        ss_hpl.append(hpl)
        own_hpl.append(p.health.horizontal_protection_m or math.inf)
    named = max(votes, key=lambda a: votes[a]) if any(votes.values()) else None
    return {"poses": poses_n, "beyond": beyond, "alarmed": alarmed,
            "ss_hpl": float(np.median(ss_hpl)) if ss_hpl else math.nan,
            "own_hpl": float(np.median(own_hpl)) if own_hpl else math.nan,
            "named": float(named == case.anchor) if case.anchor >= 0 else math.nan}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--report", action="store_true", help="the report seeds (from 1000)")
    args = ap.parse_args()
    first = REPORT_SEEDS_FROM if args.report else 0
    rows: dict[str, list[tuple[dict[str, float], dict[str, float]]]] = {k: [] for k in FAULTS}
    for seed in range(first, first + args.cases):
        case = draw_case(seed)
        rows[case.fault].append((run(case, False), run(case, True)))
    print(f"solution separation, offline (independent sub-filters), seeds {first}.."
          f"{first + args.cases - 1}; P_fa {P_FA}, risk {RISK}; poses after {WARM_UP_S:.0f} s")
    print(f"  {'fault':<16} {'cases':>5} {'>SS-PL faulty':>13} {'free':>6} {'alarm faulty':>12} "
          f"{'free':>6} {'named':>6} {'HPL SS/own (med)':>17}")
    for kind, pairs in rows.items():
        if not pairs:
            continue
        free, bad = [a for a, _ in pairs], [b for _, b in pairs]

        def share(runs: list[dict[str, float]], key: str) -> float:
            return sum(r[key] for r in runs) / max(sum(r["poses"] for r in runs), 1)

        named = [b["named"] for b in bad if not math.isnan(b["named"])]
        ratio = np.nanmedian([b["ss_hpl"] / b["own_hpl"] for b in bad + free])
        print(f"  {kind:<16} {len(pairs):>5} {share(bad, 'beyond'):>13.2%} "
              f"{share(free, 'beyond'):>6.2%} {share(bad, 'alarmed'):>12.1%} "
              f"{share(free, 'alarmed'):>6.1%} "
              f"{(np.mean(named) if named else math.nan):>6.0%} {ratio:>17.2f}")


if __name__ == "__main__":
    main()
