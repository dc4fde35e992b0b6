"""The random-installation campaign (uwbd.tools.campaign) draws what it says: seeded cases,
anchors a metre apart, paths inside their rooms, the fault in what the filter is told."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from uwbd.tools.campaign import FAULTS, STYLES, VEHICLES, draw_case, ranges_of, run_case, told
from uwbd.tools.simulator import simulate


def test_cases_are_seeded_and_within_their_rooms() -> None:
    assert draw_case(7) == draw_case(7) and draw_case(7) != draw_case(8)
    drawn = [draw_case(seed) for seed in range(40)]
    assert {c.fault for c in drawn} == set(FAULTS)
    assert {c.style for c in drawn} == set(STYLES) and {c.vehicle for c in drawn} == set(VEHICLES)
    # a third single ranges at 100-200 a second, the rest epochs at 10 Hz
    single = [c for c in drawn if c.sim.uwb_schedule == "round_robin"]
    assert 8 <= len(single) <= 20 and all(100 <= c.sim.uwb_rate_hz <= 200 for c in single)
    assert all(c.sim.uwb_schedule == "epoch" and c.sim.uwb_rate_hz == 10.0
               for c in drawn if c not in single)
    for c in drawn:
        anchors = np.array(c.sim.anchors_m)
        assert 4 <= len(anchors) <= 10
        gaps = [math.dist(a[:2], b[:2]) for i, a in enumerate(anchors) for b in anchors[i + 1:]]
        assert min(gaps) >= 1.0
        assert c.fault != "mounting" or c.vehicle == "ground"
        assert (c.anchor >= 0) == (c.fault in ("anchor_position", "range_offset"))


def test_the_path_stays_in_the_room_and_the_fault_is_in_what_the_filter_is_told() -> None:
    for kind in FAULTS:  # the first case of each kind
        case = next(c for c in map(draw_case, range(100)) if c.fault == kind)
        sim = simulate(case.sim)
        w, depth = case.room_m
        assert (sim.truth_p_m[:, 0] > 0).all() and (sim.truth_p_m[:, 0] < w).all()
        assert (sim.truth_p_m[:, 1] > 0).all() and (sim.truth_p_m[:, 1] < depth).all()
        right, wrong = told(case, sim, False), told(case, sim, True)
        assert right.nhc == (case.vehicle == "ground")
        if case.fault == "anchor_position":
            moved = math.dist(right.anchors_m[case.anchor], wrong.anchors_m[case.anchor])
            assert abs(moved - case.size) < 1e-9
        elif case.fault == "range_offset":
            clean, offset = ranges_of(case, sim, False), ranges_of(case, sim, True)
            diffs = {round(b.range_m - a.range_m, 9) for e, f in zip(clean, offset, strict=True)
                     for a, b in zip(e.ranges, f.ranges, strict=True) if a.anchor_id == case.anchor}
            assert diffs == {round(case.size, 9)} and wrong == right
        elif case.fault == "lever_arm":
            assert abs(math.dist(right.lever_arm_m, wrong.lever_arm_m) - case.size) < 1e-9
        else:  # the mounting, turned about the vertical by the case's angle
            turned = np.array(wrong.mounting_rotation) @ np.array(right.mounting_rotation).T
            angle = math.degrees(math.atan2(turned[1, 0], turned[0, 0]))
            assert abs((angle - case.size + 180) % 360 - 180) < 1e-6


def test_a_case_runs_and_is_scored_against_its_truth() -> None:
    case = draw_case(2)  # a drone under mixed anchors, one surveyed 1.3 m off
    free, faulty = run_case(case, False), run_case(case, True)
    assert free.poses > 500 and faulty.poses > 500
    assert free.rmse_3d_m < 0.2 and free.beyond_pl == 0 and free.healthy_beyond_alert == 0
    # (no vertical redundancy: the vertical level is over 1 m on half the poses, measured)
    assert not free.redundant and free.healthy > 0.3 * free.poses
    assert faulty.detected and faulty.named and faulty.healthy_beyond_alert == 0


def test_fault_free_runs_the_campaign_once_lost_stay_honest() -> None:
    """Two fault-free campaign cases that failed (#43): seed 37, ten anchors on a 3 m
    ceiling within ±5 cm of a plane, whose side the ranges 'decided' wrongly (4.3 m off in
    height, 'tracking'), and seed 8, a robot 3.4 m below its anchors whose every reset's fix
    was refused as too low (72 m RMSE)."""
    ceiling = run_case(draw_case(37), False)
    assert ceiling.healthy_beyond_alert == 0 and ceiling.rmse_3d_m < 0.2
    case = draw_case(8)  # (drawn with single ranges since; the case was one of epochs)
    low = run_case(dataclasses.replace(case, sim=dataclasses.replace(
        case.sim, uwb_schedule="epoch", uwb_rate_hz=10.0)), False)
    assert low.healthy_beyond_alert == 0 and low.rmse_3d_m < 1.0
