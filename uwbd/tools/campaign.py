"""Random installations, each run fault-free and with one thing wrong: the campaign that says
whether the installation checks and the protection levels hold on set-ups they were not
developed on (issue #43).

A case is drawn from its seed alone (:func:`draw_case`):

* a room 6–40 m on a side; 4–10 anchors around its walls (and, with more than six, some
  inside), their heights in one of three styles: ``flat`` (a ceiling, all within a few cm),
  ``mixed`` (anywhere from the floor to the ceiling) and ``few_high`` (low anchors with one
  or two high);
* a vehicle: a ``ground`` robot (tag 0.3–0.6 m up, no sideways motion, NHC on), a
  ``handheld`` tag (walked at ~1.2 m, pauses) or a ``drone`` (climbs and descends 0.6–2.6 m),
  driving a rounded loop of the room with stops;
* the tag's schedule: epochs of every anchor at 10 Hz (two cases in three), or single
  ranges round robin at 100–200 a second in all (as DW1000 tags in TWR send them; drawn
  from a stream of its own, so the rest of a case is the same either way);
* one fault: an anchor surveyed 0.3–2 m off in any direction (``anchor_position``), one
  anchor's ranges 0.2–1 m long or short (``range_offset``), the lever arm 0.1–0.5 m off
  (``lever_arm``), or (ground robots) the IMU's mounting typed turned 15–180° about the
  vertical (``mounting``).

The simulated sensors are always right; the fault is in what the filter is told (or, for a
range offset, in the ranges). :func:`score` compares the poses with the truth against the
issue's alert limits (0.5 m horizontal, 1.0 m vertical). Seeds 0–999 are the set to tune on;
1000 and up the set to report.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from drivers.frames import UwbRanges
from uwbd.config import parse
from uwbd.fusion.checks.separation import LEVER_MEMBER
from uwbd.fusion.filter import Filter
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import Pose
from uwbd.tools.evaluate import merge, run_filter
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import SimConfig, Simulation, simulate

NS = 1_000_000_000
FAULTS = ("anchor_position", "range_offset", "lever_arm", "mounting")
STYLES = ("flat", "mixed", "few_high")
VEHICLES = ("ground", "handheld", "drone")
HORIZONTAL_ALERT_M, VERTICAL_ALERT_M = 0.5, 1.0  # the filter is told them too (told)
# the faults that say the installation is wrong (not the estimate's own state)
INSTALLATION_FAULTS = frozenset({"anchor_inconsistent", "lever_arm_inconsistent",
                                 "mounting_inconsistent"})
REPORT_SEEDS_FROM = 1000  # seeds below: the tuning set; from here: the reported set
WARM_UP_S = 10.0  # a start may be unhealthy until its tests have one window
SINGLE_RANGE_SHARE = 1 / 3  # of the cases: single ranges (else epochs)


@dataclass(frozen=True)
class Case:
    """One installation, its run, and the fault drawn for it."""

    seed: int
    room_m: tuple[float, float]
    style: str
    vehicle: str
    sim: SimConfig
    fault: str
    anchor: int  # the anchor at fault (position, offset), else -1
    size: float  # the fault's size: m, or the mounting's turn in degrees
    direction: tuple[float, float, float]  # of a position or lever-arm fault (unit)


def _anchors(rng: np.random.Generator, w: float, depth: float, style: str
             ) -> tuple[tuple[float, float, float], ...]:
    n = int(rng.integers(4, 11))
    ceiling = float(rng.uniform(2.5, 4.0))
    spots: list[tuple[float, float]] = []
    while len(spots) < n:
        i = len(spots)
        if i >= 6 and rng.random() < 0.5:  # a pillar inside the room
            x, y = rng.uniform(0.3 * w, 0.7 * w), rng.uniform(0.3 * depth, 0.7 * depth)
        else:  # on a wall: the walls in turn, anywhere along them
            wall, s = i % 4, float(rng.uniform(0.05, 0.95))
            x, y = ((s * w, 0.1), (w - 0.1, s * depth), (s * w, depth - 0.1),
                    (0.1, s * depth))[wall]
        if all(math.hypot(x - a, y - b) >= 1.0 for a, b in spots):  # a metre apart at least
            spots.append((float(x), float(y)))
    if style == "flat":
        z = ceiling + rng.uniform(-0.05, 0.05, n)
    elif style == "mixed":
        z = rng.uniform(0.3, ceiling, n)
    else:
        z = rng.uniform(0.2, 1.2, n)
        z[rng.choice(n, size=int(rng.integers(1, 3)), replace=False)] = \
            rng.uniform(2.5, ceiling, 1)[0]
    return tuple((x, y, float(h)) for (x, y), h in zip(spots, z, strict=True))


def _loop(rng: np.random.Generator, w: float, depth: float, vehicle: str
          ) -> tuple[tuple[float, float, float], tuple[tuple[float, float, float, float], ...]]:
    """A start and segments ``(duration, speed, yaw rate, climb)``: twice round a rounded
    loop, anticlockwise, a metre or more from the walls (in a large room a part of it, each
    side at most 6 s long: about a minute and a half in all), with a still start and
    stops."""
    speed = float(rng.uniform(*{"ground": (0.3, 1.0), "handheld": (0.3, 0.6),
                                "drone": (0.5, 1.5)}[vehicle]))
    rate = 0.5
    radius = speed / rate
    margin = max(1.0, 0.1 * min(w, depth))
    sx = min(max(w - 2 * margin - 2 * radius, 0.5), 6.0 * speed)
    sy = min(max(depth - 2 * margin - 2 * radius, 0.5), 6.0 * speed)
    x0 = float(rng.uniform(margin + radius, max(w - margin - radius - sx, margin + radius)))
    y0 = float(rng.uniform(margin, max(depth - margin - 2 * radius - sy, margin)))
    z0 = {"ground": float(rng.uniform(0.3, 0.6)), "handheld": float(rng.uniform(1.0, 1.4)),
          "drone": 0.6}[vehicle]
    segs: list[tuple[float, float, float, float]] = [(5.0, 0.0, 0.0, 0.0)]  # at rest
    turn = (math.pi / 2 / rate, speed, rate, 0.0)
    climb = 0.0
    for lap in range(2):
        for k, side in enumerate((sx, sy, sx, sy)):
            if vehicle == "drone":  # up on the first lap, down on the second
                climb = (0.25 if lap == 0 else -0.25) * (1.0 if k % 2 == 0 else 0.6)
            segs.append((side / speed, speed, 0.0, climb))
            segs.append(turn)
            if rng.random() < 0.3:
                segs.append((float(rng.uniform(1.0, 4.0)), 0.0, 0.0, 0.0))  # a stop
    segs.append((3.0, 0.0, 0.0, 0.0))
    return (x0, y0, z0), tuple(segs)


def draw_case(seed: int) -> Case:
    """The installation, run and fault of ``seed`` (see module doc)."""
    rng = np.random.default_rng(seed)
    w, depth = (float(v) for v in rng.uniform(6.0, 40.0, 2))
    style = STYLES[int(rng.integers(len(STYLES)))]
    vehicle = VEHICLES[int(rng.integers(len(VEHICLES)))]
    anchors = _anchors(rng, w, depth, style)
    start, segments = _loop(rng, w, depth, vehicle)
    lever = (0.0, 0.0, float(rng.uniform(0.1, 0.4)))
    sim = SimConfig(segments=segments, start_m=start, anchors_m=anchors, lever_arm_m=lever,
                    ground_vehicle=vehicle == "ground", seed=seed)
    timing = np.random.default_rng([seed, 1])
    if timing.random() < SINGLE_RANGE_SHARE:
        sim = dataclasses.replace(sim, uwb_schedule="round_robin",
                                  uwb_rate_hz=float(timing.uniform(100.0, 200.0)))
    kinds = FAULTS if vehicle == "ground" else FAULTS[:3]
    fault = kinds[int(rng.integers(len(kinds)))]
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    size = float({"anchor_position": rng.uniform(0.3, 2.0),
                  "range_offset": rng.choice((-1.0, 1.0)) * rng.uniform(0.2, 1.0),
                  "lever_arm": rng.uniform(0.1, 0.5),
                  "mounting": rng.choice((-1.0, 1.0)) * rng.uniform(15.0, 180.0)}[fault])
    anchor = int(rng.integers(len(anchors))) if fault in FAULTS[:2] else -1
    dx, dy, dz = (float(c) for c in direction)
    return Case(seed, (w, depth), style, vehicle, sim, fault, anchor, size, (dx, dy, dz))


def told(case: Case, sim: Simulation, faulty: bool) -> FilterConfig:
    """What the filter is told: the datasheet config ``uwbd simulate`` writes (NHC and no
    height needed for a ground robot; the alert limits the runs are scored by), with the
    case's fault in it when ``faulty``."""
    # (a Nooploop tag has 8 slots: more anchors through a DWM1001's ids)
    driver = "nlink" if len(case.sim.anchors_m) <= 8 else "dwm1001"
    cfg = parse(simulation_toml(sim, driver)).filter_config()
    ground = case.vehicle == "ground"  # on a floor: NHC, and no height needed
    cfg = dataclasses.replace(cfg, nhc=ground, health=dataclasses.replace(
        cfg.health, horizontal_alert_limit_m=HORIZONTAL_ALERT_M,
        vertical_alert_limit_m=VERTICAL_ALERT_M, height_needed=not ground))
    if not faulty:
        return cfg
    d = np.array(case.direction)
    if case.fault == "anchor_position":
        anchors = dict(cfg.anchors_m)
        x, y, z = (np.array(anchors[case.anchor]) + case.size * d).tolist()
        anchors[case.anchor] = (x, y, z)
        return dataclasses.replace(cfg, anchors_m=anchors)
    if case.fault == "lever_arm":
        x, y, z = (np.array(cfg.lever_arm_m) + case.size * d).tolist()
        return dataclasses.replace(cfg, lever_arm_m=(x, y, z))
    if case.fault == "mounting":
        a = math.radians(case.size)
        turn = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                         [0.0, 0.0, 1.0]])
        r = (turn @ np.array(cfg.mounting_rotation)).tolist()
        return dataclasses.replace(cfg, mounting_rotation=(
            (r[0][0], r[0][1], r[0][2]), (r[1][0], r[1][1], r[1][2]), (r[2][0], r[2][1], r[2][2])))
    return cfg  # a range offset is in the ranges, not in the config


def ranges_of(case: Case, sim: Simulation, faulty: bool) -> list[UwbRanges]:
    """The tag's messages, with the case's range offset in them when ``faulty``."""
    if not (faulty and case.fault == "range_offset"):
        return list(sim.uwb)
    return [dataclasses.replace(e, ranges=tuple(
        dataclasses.replace(r, range_m=r.range_m + case.size) if r.anchor_id == case.anchor
        else r for r in e.ranges)) for e in sim.uwb]


@dataclass(frozen=True)
class Score:
    """One run against its truth, the poses after the warm-up."""

    poses: int
    beyond_pl: int  # horizontal error over the HPL, or vertical over the VPL
    healthy_beyond_alert: int  # healthy while over an alert limit (0.5 m h, 1.0 m v)
    healthy: int
    redundant: bool  # the layout sees the height without any one anchor (vertically_redundant)
    detected: bool  # an installation check fired: a finding, or one of INSTALLATION_FAULTS
    named: bool  # the faulted anchor named (anchor faults), the mounting said, or the
    # lever arm (the lever-arm test fired)
    rmse_3d_m: float


def score(case: Case, sim: Simulation, poses: list[Pose], findings: list[int],
          mounting_said: bool) -> Score:
    """``findings``: what the filter named after the warm-up (anchors; ``LEVER_MEMBER``:
    the lever arm), named most often first: a run names its fault when that comes first;
    ``mounting_said``: whether it said the mounting (a finding or the fault)."""
    t0 = sim.truth_t_ns[0] + WARM_UP_S * NS
    poses = [q for q in poses if q.t_ns >= t0]
    redundant = vertically_redundant(case.sim.anchors_m, sim.truth_p_m)
    if not poses:
        return Score(0, 0, 0, 0, redundant, False, False, math.nan)
    t = np.array([q.t_ns for q in poses])
    p = np.array([q.position_m for q in poses])
    truth = np.column_stack([np.interp(t, sim.truth_t_ns, sim.truth_p_m[:, i])
                             for i in range(3)])
    eh = np.linalg.norm(p[:, :2] - truth[:, :2], axis=1)
    ev = np.abs(p[:, 2] - truth[:, 2])
    hpl = np.array([q.health.horizontal_protection_m or math.inf for q in poses])
    vpl = np.array([q.health.vertical_protection_m or math.inf for q in poses])
    healthy = np.array([q.health.healthy for q in poses])
    # (a ground robot needs no height: told so, its health follows the horizontal)
    beyond_alert = (eh > HORIZONTAL_ALERT_M) | ((ev > VERTICAL_ALERT_M)
                                                & (case.vehicle != "ground"))
    detected = bool(findings) or mounting_said or any(
        f in INSTALLATION_FAULTS for q in poses for f in q.health.faults)
    first = findings[0] if findings else None
    named = first == case.anchor if case.anchor >= 0 else mounting_said \
        if case.fault == "mounting" else first == LEVER_MEMBER
    return Score(len(poses), int(((eh > hpl) | (ev > vpl)).sum()),
                 int((healthy & beyond_alert).sum()), int(healthy.sum()), redundant, detected,
                 named,
                 float(np.sqrt(np.mean(eh**2 + ev**2))))


def vertically_redundant(anchors_m: tuple[tuple[float, float, float], ...],
                         path_m: np.ndarray, max_vdop: float = 2.5) -> bool:
    """Whether the layout sees the height without any one of its anchors: along the path
    (20 points), the vertical dilution of precision of every set that leaves one anchor out,
    ``√[(HᵀH)⁻¹]_zz``, at most ``max_vdop`` at the median point (σz ≤ 2.5 σ_range, which a
    vertical alert limit of 1 m can hold at 0.1 m ranges)."""
    a = np.array(anchors_m)
    points = path_m[np.linspace(0, len(path_m) - 1, 20).astype(int)]
    for k in range(len(a)):
        rest = np.delete(a, k, axis=0)
        vdop = []
        for x in points:
            u = x - rest
            H = u / np.linalg.norm(u, axis=1)[:, None]
            try:
                vdop.append(math.sqrt(max(float(np.linalg.inv(H.T @ H)[2, 2]), 0.0)))
            except np.linalg.LinAlgError:
                vdop.append(math.inf)
        if not float(np.median(vdop)) <= max_vdop:
            return False
    return True


def run_case(case: Case, faulty: bool) -> Score:
    """One run of the case, fault-free or with its fault, scored."""
    sim = simulate(case.sim)
    cfg = told(case, sim, faulty)
    named: collections.Counter[int] = collections.Counter()  # messages naming each
    after_ns = sim.truth_t_ns[0] + WARM_UP_S * NS

    def watch(flt: Filter) -> None:  # what is named after the warm-up, message by message
        if flt.t_ns is not None and flt.t_ns >= after_ns:
            findings = flt.findings
            named.update({*findings.consistency.findings, *findings.separated,
                          # the separation's alarm names it; the lever-arm test fired
                          *([findings.suspect[0]] if findings.suspect is not None else []),
                          *([LEVER_MEMBER] if findings.lever_arm_m is not None else [])})

    poses, _, _ = run_filter(cfg, merge(sim.imu, ranges_of(case, sim, faulty)),
                             pose_period_ns=NS // 10, watch=watch)
    mounting = any("mounting" in f for q in poses if q.t_ns >= after_ns
                   for f in (*q.health.faults, *q.health.notes))
    return score(case, sim, poses, [a for a, _ in named.most_common()], mounting)


@dataclass(frozen=True)
class KindRow:
    """A fault kind over its cases: what the campaign prints."""

    kind: str
    cases: int
    beyond_pl: float  # of the faulty runs' poses
    free_beyond_pl: float  # of the fault-free runs' poses
    healthy_beyond_alert: int  # poses, faulty runs
    free_healthy_beyond_alert: int  # poses, fault-free runs
    availability: float  # fault-free poses healthy
    availability_redundant: float  # the same, on vertically redundant layouts only (NaN: none)
    availability_faulty: float  # faulty runs' poses healthy
    detected: float  # of the faulty runs
    false_alarm: float  # of the fault-free runs: an installation check fired
    named: float  # of the faulty runs (anchor faults: the anchor; mounting: said)
    rmse_ratio_median: float  # faulty over fault-free, 3D
    rmse_ratio_max: float


def run_pair(seed: int) -> tuple[str, Score, Score]:
    """A case's fault kind, its fault-free and its faulty run."""
    case = draw_case(seed)
    return case.fault, run_case(case, False), run_case(case, True)


def campaign(seeds: range, workers: int = 1) -> list[KindRow]:
    """Every case of ``seeds`` fault-free and faulty, summed per fault kind; over
    ``workers`` processes."""
    runs: dict[str, list[tuple[Score, Score]]] = {kind: [] for kind in FAULTS}
    if workers > 1:
        with concurrent.futures.ProcessPoolExecutor(workers) as pool:
            done = list(pool.map(run_pair, seeds))
    else:
        done = [run_pair(seed) for seed in seeds]
    for kind, free_run, faulty_run in done:
        runs[kind].append((free_run, faulty_run))
    rows = []
    for kind, pairs in runs.items():
        if not pairs:
            continue
        free = [a for a, _ in pairs]
        bad = [b for _, b in pairs]
        ratios = [b.rmse_3d_m / a.rmse_3d_m for a, b in pairs if a.rmse_3d_m > 0]
        rows.append(KindRow(
            kind, len(pairs), sum(b.beyond_pl for b in bad) / max(sum(b.poses for b in bad), 1),
            sum(a.beyond_pl for a in free) / max(sum(a.poses for a in free), 1),
            sum(b.healthy_beyond_alert for b in bad), sum(a.healthy_beyond_alert for a in free),
            sum(a.healthy for a in free) / max(sum(a.poses for a in free), 1),
            (sum(a.healthy for a in free if a.redundant)
             / sum(a.poses for a in free if a.redundant)
             if any(a.redundant and a.poses for a in free) else math.nan),
            sum(b.healthy for b in bad) / max(sum(b.poses for b in bad), 1),
            sum(b.detected for b in bad) / len(bad), sum(a.detected for a in free) / len(free),
            sum(b.named for b in bad) / len(bad),
            float(np.median(ratios)) if ratios else math.nan,
            max(ratios) if ratios else math.nan))
    return rows
