"""``uwbd survey``: anchors from anchor-to-anchor ranges (a TREK1000's ``ma`` lines, through
the driver) and from a moving tag's log, the files it writes, and what it says when it
cannot. Real logs on disk; the real CLI as a subprocess."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from procs import one_line, uwbd
from test_install import BLOCKER

from drivers import trek1000
from drivers.frames import AnchorPair, AnchorRanges, ImuSample, UwbRanges
from uwbd.config import parse, to_toml
from uwbd.config.model import SourceConfig
from uwbd.fusion.core.rotation import quat_to_matrix
from uwbd.fusion.models.range_model import RangeModel
from uwbd.logs.mcaplog import LogWriter, SourceInfo
from uwbd.logs.reading import read_log
from uwbd.tools.logtools import write_simulation
from uwbd.tools.sim_presets import HANDHELD_SEGMENTS, ROOM_ANCHORS_M, handheld_async
from uwbd.tools.simulator import EPOCH_NS, simulate
from uwbd.tools.survey import (
    Gauge,
    Settings,
    SurveyError,
    anchors_document,
    log_ranges,
    orientations_of,
    survey,
    with_anchors,
    without_distance_term,
)
from uwbd.tools.survey.output import turned_xyzw

PAIR_NOISE_M = 0.05
NS = 1_000_000_000


def perturbed(anchors: np.ndarray, magnitude: float, seed: int, horizontal: bool = False
              ) -> np.ndarray:
    """Each anchor moved by ``magnitude`` m in a random direction (3-D, or in x-y)."""
    d = np.random.default_rng(seed).normal(size=anchors.shape)
    if horizontal:
        d[:, 2] = 0.0
    return np.asarray(anchors + d / np.linalg.norm(d, axis=1, keepdims=True) * magnitude)


def pair_reports(anchors: np.ndarray, pairs: list[tuple[int, int]], n: int, seed: int
                 ) -> list[AnchorRanges]:
    """``n`` reports a second apart: each pair's true distance + N(0, 0.05 m)."""
    rng = np.random.default_rng(seed)
    return [AnchorRanges(EPOCH_NS + k * NS, tuple(
        AnchorPair(a, b, round(float(np.linalg.norm(anchors[a] - anchors[b])
                                     + rng.normal(0, PAIR_NOISE_M)), 3)) for a, b in pairs))
        for k in range(n)]


def in_frame(anchors: np.ndarray, origin: int, x_axis: int) -> np.ndarray:
    """The anchors in the frame with ``origin`` at x = y = 0 and ``x_axis`` on +x."""
    o, x = anchors[origin], anchors[x_axis]
    heading = math.atan2(x[1] - o[1], x[0] - o[0])
    c, s = math.cos(heading), math.sin(heading)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray((anchors - [o[0], o[1], 0.0]) @ R.T)


def rms(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


ROOM = np.array(ROOM_ANCHORS_M)
MA_PAIRS = [(0, 1), (0, 2), (1, 2)]


@pytest.fixture(scope="module")
def trek_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A TREK1000 log of ``ma`` lines only (raw bytes, as the daemon logs them): 60 reports
    of A0-A1, A0-A2, A1-A2 in the ceiling room, and its config (the anchors tape-measured:
    0.15 m off horizontally)."""
    folder = tmp_path_factory.mktemp("trek")
    tape = perturbed(ROOM, 0.15, 3, horizontal=True)
    sources = (SourceConfig("uwb", "trek1000", "/dev/ttyACM0", 115200),)
    toml = to_toml(sources, dict(enumerate(tape)), ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
                   (0, 0, 0))
    path = folder / "trek.mcap"
    with LogWriter(path, toml, (SourceInfo("uwb", "trek1000", "/dev/ttyACM0"),)) as log:
        for k, report in enumerate(pair_reports(ROOM, MA_PAIRS, 60, 1)):
            log.raw("uwb", report.t_ns, trek1000.encode(report, seq=k % 256))
    config = folder / "robot.toml"
    config.write_text(toml)
    return path, config


@pytest.fixture(scope="module")
def handheld_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated handheld run (37 s, one range a message, 8 anchors at two heights)."""
    cfg = dataclasses.replace(handheld_async(5), segments=HANDHELD_SEGMENTS[:8])
    path = tmp_path_factory.mktemp("hand") / "hand.mcap"
    write_simulation(simulate(cfg), path)
    return path


def test_anchor_ranges_recover_a_known_layout_in_the_users_frame() -> None:
    # five anchors, all ten pairs, 60 reports each with a few NLOS bursts; the config's
    # horizontal positions 0.15 m off, its heights right (held: the anchors are coplanar
    # within 0.3 m)
    true = np.vstack([ROOM, [[4.0, 3.0, 2.45]]])
    pairs = [(a, b) for a in range(5) for b in range(a + 1, 5)]
    reports = pair_reports(true, pairs, 60, 2)
    for k in (5, 17, 40):  # +1 m on one pair now and then: the median does not move
        reports[k] = AnchorRanges(reports[k].t_ns, tuple(
            dataclasses.replace(p, range_m=p.range_m + 1.0) if (p.anchor_a, p.anchor_b) == (0, 2)
            else p for p in reports[k].pairs))
    tape = perturbed(true, 0.15, 4, horizontal=True)
    result = survey(dict(enumerate(tape)), [], reports, Settings(gauge=Gauge(0, 1, 3)))
    got = np.array([result.anchors[a].position_m for a in range(5)])
    want = in_frame(true, 0, 1)
    # in the user's frame: 0 at the origin, 1 on +x, 3 on +y
    assert got[0, :2] == pytest.approx([0, 0], abs=1e-9) and got[1, 1] == pytest.approx(0)
    assert got[3, 1] > 0
    # within the noise: a 0.05 m range noise over 60 reports is ~8 mm per pair
    assert rms(got - want) < 0.02, got - want
    assert np.all(np.abs(got[:, 2] - true[:, 2]) < 1e-9)  # heights held
    assert any("heights held" in n for n in result.notes)
    sigma = np.array([result.anchors[a].sigma_m for a in range(5)])
    assert sigma[0, 0] == 0 and sigma[1, 1] == 0 and np.all(sigma[2, :2] > 0.001)
    assert np.all(sigma[:, 2] == 0)  # held
    assert np.all(np.abs(got - want)[:, :2] < 4 * sigma[:, :2] + 1e-6)
    assert [p.outliers for p in result.pairs if (p.anchor_a, p.anchor_b) == (0, 2)] == [3]
    # in the config's frame (no --origin): the same shape, placed to fit the tape measure
    loose = survey(dict(enumerate(tape)), [], reports)
    shape = np.array([loose.anchors[a].position_m for a in range(5)])
    for a, b in pairs:
        assert math.dist(shape[a], shape[b]) == pytest.approx(math.dist(true[a], true[b]),
                                                              abs=0.02)


def test_trek1000_ma_lines_fix_the_triangle_and_nothing_else(trek_log: tuple[Path, Path]
                                                             ) -> None:
    path, config_path = trek_log
    uwb, reports = log_ranges(read_log(path))  # the raw bytes through the TREK1000 driver
    assert not uwb and len(reports) == 60 and {len(r.pairs) for r in reports} == {3}
    config = parse(config_path.read_text())
    result = survey(config.anchors_m, uwb, reports, Settings(gauge=Gauge(0, 1)))
    got = {a: np.array(e.position_m) for a, e in result.anchors.items()}
    for a, b in MA_PAIRS:  # the three sides, within the noise (and the mm of the wire)
        assert math.dist(got[a], got[b]) == pytest.approx(math.dist(ROOM[a], ROOM[b]),
                                                          abs=0.02)
    assert got[2][1] > 0  # the side the config puts A2 on
    # A3 has no ranges: as configured, carried into the frame 0 -> 1 defines
    assert not result.anchors[3].surveyed and result.anchors[3].sigma_m[0] == 0.2
    tape = np.array([config.anchors_m[a] for a in range(4)])
    assert got[3] == pytest.approx(in_frame(tape, 0, 1)[3], abs=1e-9)
    assert any("no range reaches anchor(s) 3" in n for n in result.notes)


def test_tag_log_refinement_halves_a_tape_measure_error(handheld_log: Path) -> None:
    # the anchors 0.15 m off in 3-D; heights measured (--height) and the frame the user's:
    # the ranges then fix the rest; a log's own tag ranges (decoded from its raw bytes)
    contents = read_log(handheld_log)
    uwb, reports = log_ranges(contents)
    assert len(uwb) > 5000 and not reports
    assert {len(m.ranges) for m in uwb} == {1}  # one range a message: 0.2 s windows
    configured = parse(contents.metadata["config_toml"]).anchors_m  # the true ones
    true = np.array([configured[a] for a in range(8)])
    heights = {a: float(z) for a, z in enumerate(true[:, 2])}
    want = in_frame(true, 0, 1)
    for seed in (0, 1):
        tape = perturbed(true, 0.15, seed)
        tape[:, 2] = true[:, 2]
        before = rms(in_frame(tape, 0, 1) - want)
        result = survey(dict(enumerate(tape)), uwb, [],
                        Settings(gauge=Gauge(0, 1, 3), heights_m=heights))
        got = np.array([result.anchors[a].position_m for a in range(8)])
        assert rms(got - want) < before / 2, (seed, before, rms(got - want))
        assert result.tag_positions > 150 and 0.5 < result.sigma0 < 1.5
        assert np.all(got[:, 2] == true[:, 2])


def test_the_distance_term_comes_off_the_ranges_before_the_survey(handheld_log: Path,
                                                                   tmp_path: Path) -> None:
    """Ranges that read ``0.15 ln(d / 1 m)`` long, as a DW1000's grow with the distance:
    surveyed as they are, the layout stretches (0.29 m RMS); with the config's distance
    term taken off first (as ``uwbd survey`` does when ``[range_model] log_distance_m`` is
    set, and says so), it comes out as from clean ranges (0.061 against 0.064 m)."""
    contents = read_log(handheld_log)
    uwb, _ = log_ranges(contents)
    configured = parse(contents.metadata["config_toml"]).anchors_m  # the true ones
    true = np.array([configured[a] for a in range(8)])
    want = in_frame(true, 0, 1)
    tape = perturbed(true, 0.15, 0)
    tape[:, 2] = true[:, 2]
    settings = Settings(gauge=Gauge(0, 1, 3), heights_m=dict(enumerate(true[:, 2])))
    longer = [dataclasses.replace(m, ranges=tuple(
        dataclasses.replace(r, range_m=r.range_m + 0.15 * math.log(r.range_m))
        for r in m.ranges)) for m in uwb]

    def error(ranges: list[UwbRanges]) -> float:
        result = survey(dict(enumerate(tape)), ranges, [], settings)
        return rms(np.array([result.anchors[a].position_m for a in range(8)]) - want)

    # from the clean ranges: 0.064 m RMS (the tape 0.166 m)
    left_in = error(longer)
    taken_off = error(without_distance_term(RangeModel(log_distance_m=0.15), longer, [])[0])
    assert left_in > 0.2 and taken_off < 0.075, (left_in, taken_off)
    said = uwbd("survey", str(handheld_log), "--set", "range_model.log_distance_m=0.1",
                cwd=tmp_path)
    assert said.returncode == 0, said.stderr
    assert "distance term taken off first (range_model.log_distance_m = 0.1)" in said.stdout


def test_with_anchors_keeps_the_configs_spelling_and_the_rest() -> None:
    text = ('[anchors]\n"0x10" = [0.0, 0.0, 2.0]\n"17" = [5.0, 0.0, 2.0]\n"18" = [0.0, 4.0, 2.0]\n'
            '"19" = { position_m = [5.0, 4.0, 2.1], orientation_xyzw = [0.0, 0.0, 1.0, 0.0] }'
            '\n\n[fusion]\nrange_sigma_m = 0.08\n')
    truth = {16: (0.0, 0.0, 2.0), 17: (5.1, 0.0, 2.0), 18: (0.0, 4.1, 2.0), 19: (5.1, 4.1, 2.1)}
    pairs = [(a, b) for a in truth for b in truth if a < b]
    arr = np.array([truth[a] for a in sorted(truth)])
    index = {a: i for i, a in enumerate(sorted(truth))}
    reports = [AnchorRanges(r.t_ns, tuple(AnchorPair(sorted(truth)[p.anchor_a],
                                                     sorted(truth)[p.anchor_b], p.range_m)
                                          for p in r.pairs))
               for r in pair_reports(arr, [(index[a], index[b]) for a, b in pairs], 30, 5)]
    result = survey(parse(text).anchors_m, [], reports, Settings(gauge=Gauge(16, 17, 18)))
    out = with_anchors(text, result, "surveyed", "cfg.toml")
    assert "\n0x10 = [0.0, 0.0, 2.0]\n" in out and "range_sigma_m = 0.08" in out
    parsed = parse(out)
    assert parsed.anchors_m[17][0] == pytest.approx(5.1, abs=0.02)
    assert parsed.anchors_m[19] == pytest.approx(truth[19], abs=0.03)
    assert parsed.anchor_axes[19] == parse(text).anchor_axes[19]  # its orientation kept


def test_an_anchors_orientation_turns_with_the_surveyed_frame() -> None:
    """An orientation the config gives stays with its anchor in both outputs, turned by
    the survey's frame turn about z (``p' = R(turn) p``: the axes' rows turn alike)."""
    q = [0.1, 0.2, 0.3, math.sqrt(1 - 0.14)]
    turned = turned_xyzw(q, 37.0)
    c, s = math.cos(math.radians(37.0)), math.sin(math.radians(37.0))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    def rows(v: list[float]) -> np.ndarray:
        return quat_to_matrix(np.array([v[3], v[0], v[1], v[2]]))
    assert rows(turned) == pytest.approx(Rz @ rows(q), abs=1e-8)
    # the config's layout turned 37° from the gauge's: anchor 1 is then put on +x
    truth = np.array([[1.0, 1.0, 2.0], [1.0 + 5.0 * c, 1.0 + 5.0 * s, 2.0],
                      [1.0 - 4.0 * s, 1.0 + 4.0 * c, 2.0],
                      [1.0 + 5.0 * c - 4.0 * s, 1.0 + 5.0 * s + 4.0 * c, 2.1]])
    text = "[anchors]\n" + "".join(f"{a} = {p.tolist()}\n" for a, p in enumerate(truth[:3])) \
        + f"3 = {{ position_m = {truth[3].tolist()}, orientation_xyzw = {q} }}\n"
    pairs = [(a, b) for a in range(4) for b in range(a + 1, 4)]
    result = survey(parse(text).anchors_m, [], pair_reports(truth, pairs, 30, 5),
                    Settings(gauge=Gauge(0, 1, 2)))
    assert result.frame_turn_deg == pytest.approx(-37.0, abs=0.5)
    document = parse(anchors_document(result, "surveyed", orientations_of(text)))
    rewritten = parse(with_anchors(text, result, "surveyed", "cfg.toml"))
    for config in (document, rewritten):
        assert np.array(config.anchor_axes[3]) == pytest.approx(
            rows(turned_xyzw(q, result.frame_turn_deg)), abs=1e-6)


def test_gauge_mistakes_are_one_line_each() -> None:
    anchors = dict(enumerate(ROOM))
    reports = pair_reports(ROOM, MA_PAIRS, 5, 1)
    for gauge, says in ((Gauge(0, None), "go together"), (Gauge(0, 0), "three different"),
                        (Gauge(7, 1), "--origin 7: no such anchor (anchors: 0, 1, 2, 3)"),
                        (Gauge(0, 1, 2), None)):
        if says is None:  # the config puts A2 on the +y side of 0 -> 1: fine
            survey(anchors, [], reports, Settings(gauge=gauge))
            continue
        with pytest.raises(SurveyError, match=re.escape(says)):
            survey(anchors, [], reports, Settings(gauge=gauge))
    mirrored = {a: (x, -y, z) for a, (x, y, z) in anchors.items()}
    with pytest.raises(SurveyError, match="mirror image"):
        survey(mirrored, [], reports, Settings(gauge=Gauge(0, 1, 2)))
    with pytest.raises(SurveyError, match="nothing to survey"):
        survey(anchors, [], [])


def test_cli_writes_the_anchors_and_the_config_it_says(trek_log: tuple[Path, Path],
                                                       tmp_path: Path) -> None:
    path, config = trek_log
    table, out = tmp_path / "anchors.toml", tmp_path / "robot-surveyed.toml"
    result = uwbd("survey", str(path), "--origin", "0", "--x-axis", "1", "-o", str(table),
                  "--write-config", str(config), str(out))
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    assert f"wrote {table}" in result.stdout and f"wrote {out}" in result.stdout
    assert "anchor-to-anchor ranges" in result.stdout and "heights held" in result.stdout
    anchors = parse(table.read_text()).anchors_m
    rewritten = parse(out.read_text())
    assert rewritten.anchors_m == anchors and set(anchors) == {0, 1, 2, 3}
    assert rewritten.sources == parse(config.read_text()).sources
    assert anchors[0][:2] == (0.0, 0.0) and anchors[1][1] == 0.0
    for a, b in MA_PAIRS:
        assert math.dist(anchors[a], anchors[b]) == pytest.approx(math.dist(ROOM[a], ROOM[b]),
                                                                  abs=0.02)
    # the printed table holds what was written
    row = next(line.split() for line in result.stdout.splitlines()
               if line.split()[:1] == ["2"])
    assert [float(v) for v in row[1:4]] == pytest.approx(list(anchors[2]), abs=1e-3)


def test_cli_errors_are_one_line_exit_2(trek_log: tuple[Path, Path], tmp_path: Path) -> None:
    path, _ = trek_log
    imu_only = tmp_path / "imu.mcap"
    with LogWriter(imu_only, to_toml((), dict(enumerate(ROOM)), ((1, 0, 0), (0, 1, 0),
                                                                  (0, 0, 1)), (0, 0, 0))) as log:
        for k in range(20):
            log.frame(ImuSample(EPOCH_NS + k * 5_000_000, (0.0, 0.0, 9.8), (0.0, 0.0, 0.0)))
    one_line(uwbd("survey", str(imu_only)), 2, str(imu_only), "nothing to survey from",
             "no UWB ranges")
    one_line(uwbd("survey", str(path), "--origin", "9", "--x-axis", "1"), 2,
             "--origin 9: no such anchor (anchors: 0, 1, 2, 3)")
    missing = tmp_path / "nowhere" / "anchors.toml"
    one_line(uwbd("survey", str(path), "-o", str(missing)), 2, "cannot write the anchors",
             "does not exist")
    assert not missing.parent.exists()
    (tmp_path / "sitecustomize.py").write_text(BLOCKER)  # as on the robot: no tools extra
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    one_line(uwbd("survey", str(path), env=env), 2, "survey needs the tools extra",
             "pip install 'uwbd[tools]'")
