"""The range model: the tag antenna's direction term (real spherical harmonics) and the
anchors' antenna delays; in the filter, in the config, and fitted by ``uwbd calibrate-ranges``
from a calibration recording imported with ``uwbd import inrol``. Real logs on disk, the
real CLI as a subprocess."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer
from procs import one_line, uwbd

from drivers.frames import UwbRanges
from uwbd.config import ConfigError, apply_overrides, parse
from uwbd.fusion.core.rotation import quat_from_euler, quat_to_matrix
from uwbd.fusion.filter import Filter
from uwbd.fusion.models.range_model import RangeModel, basis, n_coefficients
from uwbd.fusion.settings import IDENTITY3, FilterConfig, RobustPolicy
from uwbd.tools.evaluate import merge, run_filter, score_poses
from uwbd.tools.importer import load_inrol
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.range_calibration import calibrate, range_samples
from uwbd.tools.range_noise import nlos_tail
from uwbd.tools.sim_presets import handheld_async
from uwbd.tools.simulator import simulate

S3 = math.sqrt(3.0)
ANCHORS = {1: (0.0, 0.0, 0.3), 2: (5.0, 0.0, 0.3), 3: (5.0, 4.0, 0.3), 4: (0.0, 4.0, 0.3),
           5: (0.0, 0.0, 2.4), 6: (5.0, 0.0, 2.4), 7: (5.0, 4.0, 2.4), 8: (0.0, 4.0, 2.4)}
DELAYS = {1: -0.12, 2: 0.02, 3: -0.08, 4: 0.03, 5: 0.0, 6: 0.01, 7: -0.02, 8: -0.04}
PHASE_CENTRE_M = np.array([0.05, 0.01, 0.09])  # tag axes
LOG_DISTANCE_M = 0.1  # the ranges' distance term: 0.1 ln(d / 1 m)
H = math.sqrt(0.5)
# the anchors' antennas (x, y, z, w, their axes in the room's): the low ones turned about z
# by 90° each, the high ones tilted 45° about x
ORIENTATIONS = {1: (0, 0, 0, 1), 2: (0, 0, H, H), 3: (0, 0, 1, 0), 4: (0, 0, H, -H),
                **dict.fromkeys((5, 6, 7, 8), (math.sin(math.pi / 8), 0, 0,
                                               math.cos(math.pi / 8)))}


def axes_of(q: tuple[float, ...]) -> np.ndarray:
    """An orientation (x, y, z, w) as rows: the anchor's axes -> the room's."""
    x, y, z, w = q
    return quat_to_matrix(np.array([w, x, y, z]))


def sphere(n: int) -> np.ndarray:
    """``n`` near-uniform unit vectors (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = k * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def test_the_harmonics_have_mean_square_one_and_are_orthogonal() -> None:
    Y = basis(sphere(40_000), 3)
    assert Y.shape == (40_000, n_coefficients(3)) == (40_000, 15)
    gram = Y.T @ Y / len(Y)
    assert np.abs(gram - np.eye(15)).max() < 2e-3


def test_degree_one_is_a_phase_centre_and_higher_degrees_come_off_the_ranges() -> None:
    c = (0.01, 0.02, -0.03, 0.004, -0.005, 0.006, 0.007, -0.008)
    model = RangeModel(2, c)
    assert model.phase_centre_m() == pytest.approx(S3 * np.array([-0.03, 0.01, 0.02]))
    # far anchors: |d + R δ| − |d| → δ·u, the degree-1 term of the ray's direction
    R = quat_to_matrix(quat_from_euler(0.1, -0.2, 1.0))
    d = sphere(50) * 1e4
    u = d @ R / 1e4
    shift = np.linalg.norm(d + R @ model.phase_centre_m(), axis=1) - np.linalg.norm(d, axis=1)
    assert shift == pytest.approx(basis(u, 1) @ np.array(c[:3]), abs=1e-6)
    anchors = -d[:, :] + np.array([1.0, 2.0, 3.0])
    higher = model.higher_delay_m(quat_from_euler(0.1, -0.2, 1.0), (1.0, 2.0, 3.0), (0, 0, 0),
                                  anchors)
    assert higher == pytest.approx(basis(u, 2)[:, 3:] @ np.array(c[3:]))
    assert not RangeModel().enabled and RangeModel(1, (0, 0, 0)).enabled
    with pytest.raises(ValueError, match="degree 2 takes 8 coefficients, got 3"):
        RangeModel(2, (0.0, 0.0, 0.0))


BASE = """
[[sources]]
name = "uwb"
driver = "dwm1001"
port = "/dev/ttyACM0"
"""


def test_the_config_section_parses_into_the_filter_and_is_off_by_default() -> None:
    assert parse(BASE).filter_config().range_model == RangeModel()
    got = parse(BASE + """
[range_model]
tag_degree = 1
tag_coefficients_m = [0.001, 0.05, 0.03]
tag_mounting = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
anchor_delays_m = { 1 = -0.12, 0x1151 = 0.02 }
log_distance_m = 0.12
calibrated_from = "calib.mcap"
""").filter_config().range_model
    assert got.degree == 1 and got.coefficients_m == (0.001, 0.05, 0.03)
    assert got.log_distance_m == 0.12
    assert got.anchor_delays_m == ((1, -0.12), (0x1151, 0.02))
    # the tag's x axis is the body's y: the phase centre turns with it
    assert got.phase_centre_m() == pytest.approx(S3 * np.array([-0.001, 0.03, 0.05]))


def test_an_anchor_with_an_orientation_gives_the_anchors_term_its_axes() -> None:
    """``[anchors]`` in the table form (position and the antenna's orientation, x y z w:
    here turned 90° about z), beside the plain one; anchors without an orientation take
    no anchors' term, and check-config says so."""
    config = parse(BASE + """
[anchors]
1 = { position_m = [0.0, 0.0, 2.0], orientation_xyzw = [0.0, 0.0, 0.70710678, 0.70710678] }
2 = [5.0, 0.0, 2.0]
3 = [5.0, 4.0, 2.0]
[range_model]
anchor_degree = 1
anchor_coefficients_m = [0.01, 0.02, 0.03]
""")
    assert config.anchors_m[1] == (0.0, 0.0, 2.0)
    model = config.filter_config().range_model
    assert model.anchor_degree == 1 and model.anchor_coefficients_m == (0.01, 0.02, 0.03)
    (axes_of, rows), = model.anchor_axes
    assert axes_of == 1
    assert np.array(rows) == pytest.approx(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    # the tag 1 m east of anchor 1 is along the anchor's -y: c_1,-1 √3 (-1); anchor 2: none
    term = model.anchor_term_m([1, 2], np.array([[0.0, 0.0, 2.0], [5.0, 0.0, 2.0]]),
                               np.array([1.0, 0.0, 2.0]))
    assert term == pytest.approx([-S3 * 0.01, 0.0])
    assert any("range_model.anchor_degree: no orientation for anchor(s) 2, 3" in w
               for w in config.warnings), config.warnings
    loose = parse(BASE + '[fusion]\nmode = "loose"\n[range_model]\nanchor_degree = 1\n'
                  'anchor_coefficients_m = [0.0, 0.0, 0.0]\n')
    assert any("loose mode's fixes take no anchors' term" in w for w in loose.warnings)


@pytest.mark.parametrize(("section", "message"), [
    ("tag_degree = 2\ntag_coefficients_m = [0.1, 0.0, 0.0]",
     "range_model.tag_coefficients_m: degree 2 takes 8 coefficients"),
    ("tag_coefficients_m = [0.1, 0.0, 0.0]",
     "range_model.tag_coefficients_m: given without range_model.tag_degree"),
    ("tag_degree = 1\ntag_coefficients_m = [0.1, 5.0, 0.0]",
     "range_model.tag_coefficients_m: element 1 is 5 m"),
    ("tag_degree = 4", "range_model.tag_degree: must be zero or more and at most 3, got 4"),
    ("anchor_delays_m = { x = 0.1 }", "range_model.anchor_delays_m.x: not an anchor id"),
    ("anchor_delays_m = { 3 = 12.0 }", "range_model.anchor_delays_m.3: 12 m"),
    ("tag_degree = 1\ntag_coefficients_m = [0.0, 0.0, 0.0]\ntag_mounting = [[1, 0, 0], "
     "[0, 1, 0], [0, 0, -1]]", "range_model.tag_mounting: rows must be orthonormal"),
    ("tag_degre = 1", "range_model.tag_degre: unknown key"),
    ("log_distance_m = 12.0", "range_model.log_distance_m: must be zero or more and at most "
     "0.5, got 12"),
    ("log_distance_m = -0.1", "range_model.log_distance_m: must be zero or more"),
    ("anchor_degree = 1\nanchor_coefficients_m = [0.1]",
     "range_model.anchor_coefficients_m: anchor degree 1 takes 3 coefficients (degrees 1..1, "
     "m = -l..l each), got 1"),
    ("anchor_coefficients_m = [0.1, 0.0, 0.0]",
     "range_model.anchor_coefficients_m: given without range_model.anchor_degree"),
    ("anchor_degree = 1\nanchor_coefficients_m = [0.0, 2.0, 0.0]",
     "range_model.anchor_coefficients_m: element 1 is 2 m"),
])
def test_config_mistakes_are_errors_naming_the_key(section: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse(BASE + "[range_model]\n" + section + "\n", "robot.toml")
    assert f"robot.toml: {message}" in str(err.value), str(err.value)


@pytest.mark.parametrize(("entry", "message"), [
    ("{ position_m = [0, 0, 2], orientation_xyzw = [0, 0, 0.5, 0.5] }",
     "anchors.1.orientation_xyzw: a quaternion of norm 0.707107: expected a unit quaternion"),
    ("{ position_m = [0, 0, 2], orientation_xyzw = [0, 0, 1] }",
     "anchors.1.orientation_xyzw: expected [qx, qy, qz, qw] of finite numbers"),
    ("{ position = [0, 0, 2] }", "anchors.1.position: unknown key (an anchor takes "
     "position_m and orientation_xyzw)"),
    ("{ orientation_xyzw = [0, 0, 0, 1] }", "anchors.1.position_m: expected [x, y, z]"),
    ('"here"', "anchors.1: expected [x, y, z] of finite numbers, or { position_m"),
])
def test_an_anchor_entry_mistake_is_an_error_naming_it(entry: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse(BASE + f"[anchors]\n1 = {entry}\n", "robot.toml")
    assert f"robot.toml: {message}" in str(err.value), str(err.value)


def test_an_anchor_without_a_delay_while_the_delay_states_are_off_is_a_warning() -> None:
    base = BASE + "[anchors]\n1 = [0, 0, 2]\n2 = [5, 0, 2]\n3 = [5, 4, 2]\n"
    delays = "[range_model]\nanchor_delays_m = { 1 = 0.05, 3 = -0.02 }\n"
    off = "[fusion]\nrange_bias_states = false\n"
    def warned(text: str) -> list[str]:
        return [w for w in parse(text).warnings if "range_model" in w]

    said = warned(base + off + delays)
    assert len(said) == 1 and "range_model.anchor_delays_m: no delay for anchor(s) 2 and " \
        "fusion.range_bias_states = false" in said[0], said
    assert not warned(base + delays)  # the states estimate what is not given
    assert not warned(base + off)  # no delays calibrated at all: a choice
    loose = '[fusion]\nmode = "loose"\n[range_model]\ntag_degree = 2\ntag_coefficients_m = ' \
        + str([0.0] * 8) + "\n"
    assert "loose mode's fixes take degree 1" in " ".join(warned(base + loose))


def run(cfg: FilterConfig, sim: object) -> tuple[list, Filter]:
    poses, _, flt = run_filter(cfg, merge(sim.imu, sim.uwb))  # type: ignore[attr-defined]
    return poses, flt


def test_the_filter_applies_the_term_once_the_heading_is_known_and_says_so_before() -> None:
    """A tag whose phase centre is 12 cm off the configured antenna (the simulator's lever
    arm is where the ranges come from): the term in [range_model] puts it back."""
    offset = np.array([0.06, 0.0, 0.10])
    true_lever = tuple(float(c) for c in np.array([0.0, 0.0, 0.1]) + offset)
    sim = simulate(dataclasses.replace(handheld_async(3), lever_arm_m=true_lever))
    told = parse(simulation_toml(sim)).filter_config()
    plain = dataclasses.replace(told, lever_arm_m=(0.0, 0.0, 0.1))
    x, y, z = offset / S3
    modelled = dataclasses.replace(plain, range_model=RangeModel(1, (y, z, x)))
    scores = {}
    for name, cfg in (("plain", plain), ("modelled", modelled), ("told", told)):
        poses, flt = run(cfg, sim)
        scores[name] = score_poses(poses, sim.truth_t_ns, sim.truth_p_m, 10.0).rmse_3d_m
        held = [p for p in poses if "range_model_held" in p.health.notes]
        if name == "modelled":
            assert held and held[-1].t_ns < poses[-1].t_ns and flt.est.aligned
            assert all(p.health.phase.value != "tracking" for p in held)
            assert np.allclose(flt.est.lever, np.array(plain.lever_arm_m) + offset)
            flt.recovery.restart(poses[-1].t_ns, "a test")  # the heading is lost: so is the term
            assert np.array_equal(flt.est.lever, plain.lever_arm_m)
        else:
            assert not held
    assert scores["modelled"] < 0.85 * scores["plain"], scores
    assert scores["modelled"] < 1.4 * scores["told"], scores


def test_a_model_of_zeros_gives_the_very_same_poses_as_none() -> None:
    """Degree 1 and 2 with every coefficient and every anchor delay zero, and the anchors'
    term of zeros, take the model's every path (the phase centre, the higher degrees, the
    delays, the anchors' term) and change no pose."""
    sim = simulate(handheld_async(4))  # long enough for the heading to be found
    cfg = parse(simulation_toml(sim)).filter_config()
    assert not cfg.range_model.enabled
    a, _ = run(cfg, sim)
    zero_delays = tuple((i, 0.0) for i in range(len(sim.config.anchors_m)))
    for degree in (1, 2):
        zeros = RangeModel(degree, (0.0,) * n_coefficients(degree), anchor_delays_m=zero_delays,
                           anchor_degree=degree,
                           anchor_coefficients_m=(0.0,) * n_coefficients(degree),
                           anchor_axes=((0, IDENTITY3), (3, IDENTITY3)))
        b, flt = run(dataclasses.replace(cfg, range_model=zeros), sim)
        assert flt.est.aligned and any("range_model_held" in p.health.notes for p in b)
        assert [p.position_m for p in a] == [p.position_m for p in b] and a


def test_calibrated_anchor_delays_do_what_the_delay_states_would() -> None:
    """Anchors whose antennas add 3-50 cm to their ranges (σ 15 cm): taken off by the
    calibrated delays, the filter without delay states is as good as with them, and far
    better than with neither."""
    sim = simulate(dataclasses.replace(handheld_async(3), range_bias_sigma_m=0.15))
    cfg = parse(simulation_toml(sim)).filter_config()
    neither = dataclasses.replace(cfg, range_bias_states=False)
    delays = tuple((i, float(b)) for i, b in enumerate(sim.range_bias_m))
    scores = {}
    for name, c in (("states", cfg), ("neither", neither), *(
            (f"delays, degree {d}", dataclasses.replace(neither, range_model=RangeModel(
                d, (0.0,) * n_coefficients(d), anchor_delays_m=delays))) for d in (1, 2))):
        poses, _ = run(c, sim)
        scores[name] = score_poses(poses, sim.truth_t_ns, sim.truth_p_m, 10.0).rmse_3d_m
    for d in (1, 2):
        assert scores[f"delays, degree {d}"] < 0.6 * scores["neither"], scores
        assert scores[f"delays, degree {d}"] < 1.1 * scores["states"], scores


def calibration_recording(root: Path, seconds: float = 80.0, seed: int = 0,
                          attitude: bool = True,
                          correlated: tuple[float, float] = (0.0, 1.0),
                          log_distance_m: float = LOG_DISTANCE_M,
                          anchor_term_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:
    """A range-model calibration recording in the inrol layout (``anchor.txt``,
    ``tag_pose.txt``, ``uwb.txt``): the tag walked round the room turning through every
    heading, each range with its anchor's delay, the tag's phase-centre term, the distance
    term ``log_distance_m`` ln(d / 1 m), the anchors' degree-1 term ``anchor_term_m`` (the
    ray in each anchor's axes, ``ORIENTATIONS``), noise (white, and ``correlated`` = (σ m, τ s) of a
    Gauss–Markov error per anchor) and a few one-sided NLOS ranges."""
    rng = np.random.default_rng(seed)
    root.mkdir()
    lines = ["# anchor_id tx ty tz qx qy qz qw"]
    lines += [f"{a} {x} {y} {z} " + " ".join(map(str, ORIENTATIONS[a]))
              for a, (x, y, z) in ANCHORS.items()]
    (root / "anchor.txt").write_text("\n".join(lines) + "\n")
    t = np.arange(0.0, seconds, 0.01)
    p = np.column_stack([2.5 + 1.5 * np.cos(0.21 * t), 2.0 + 1.2 * np.sin(0.33 * t),
                         1.0 + 0.3 * np.sin(0.5 * t)])
    yaw, roll, pitch = 0.7 * t, 0.2 * np.sin(0.9 * t), 0.2 * np.cos(0.7 * t)
    q = np.array([quat_from_euler(r, pt, y) for r, pt, y in zip(roll, pitch, yaw, strict=True)])
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [f"{ti:.6f} {x:.6f} {y:.6f} {z:.6f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}"
              for ti, (x, y, z), (qw, qx, qy, qz)
              in zip(t, p, q if attitude else np.tile((1.0, 0, 0, 0), (len(t), 1)),
                     strict=True)]
    (root / "tag_pose.txt").write_text("\n".join(lines) + "\n")
    lines = ["# index timestamp anchor_id r"]
    ids = list(ANCHORS)
    sigma_c, tau_c = correlated
    slow = {a: (0.0, rng.normal(0, sigma_c)) for a in ids}  # each anchor's (t, error)
    for k, tr in enumerate(np.arange(0.05, seconds - 0.05, 1 / 160)):
        a = ids[k % len(ids)]
        i = int(tr / 0.01)
        f = tr / 0.01 - i
        pos = p[i] * (1 - f) + p[i + 1] * f
        R = quat_to_matrix(q[i])
        fade = math.exp(-(tr - slow[a][0]) / tau_c)
        slow[a] = (tr, fade * slow[a][1] + rng.normal(0, sigma_c * math.sqrt(1 - fade**2)))
        ray = pos + R @ PHASE_CENTRE_M - np.array(ANCHORS[a])
        d = float(np.linalg.norm(ray))
        u_anchor = axes_of(ORIENTATIONS[a]).T @ ray / d  # in the anchor's axes
        anchor_term = float(np.array(anchor_term_m) @ basis(u_anchor[None, :], 1)[0])
        r = (d + log_distance_m * math.log(d) + DELAYS[a] + anchor_term + slow[a][1]
             + rng.normal(0, 0.03)
             + (rng.uniform(0.3, 1.0) if rng.random() < 0.04 else 0.0))
        lines.append(f"{k} {tr:.6f} {a} {r:.6f}")
    (root / "uwb.txt").write_text("\n".join(lines) + "\n")
    return root


def test_calibrate_ranges_recovers_the_term_and_the_delays(tmp_path: Path) -> None:
    data = calibration_recording(tmp_path / "calib")
    imp = uwbd("import", "inrol", str(data), "-o", "calib.mcap", cwd=tmp_path)
    assert imp.returncode == 0, imp.stderr
    assert "no IMU (a range-model calibration recording" in imp.stdout
    base = tmp_path / "robot.toml"
    base.write_text(BASE + "[anchors]\n" + "".join(f"{a} = [{x}, {y}, {z}]\n"
                                                 for a, (x, y, z) in ANCHORS.items()))
    done = uwbd("calibrate-ranges", "calib.mcap", "-o", "rm.toml", "--write-config",
                str(base), "calibrated.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "ranges to 8 anchors over 80 s against the truth" in out
    assert "degree 1:" in out and "<- fitted" in out and "degree 3:" in out
    assert "wrote rm.toml" in out and "wrote calibrated.toml" in out
    snippet = parse(BASE + (tmp_path / "rm.toml").read_text())
    written = parse((tmp_path / "calibrated.toml").read_text())
    model = written.filter_config().range_model
    assert model == snippet.filter_config().range_model
    assert written.filter_config().range_bias_states is False  # the delays are known
    # the recording's 4 % of NLOS ranges (0.3-1 m long, noise 0.03 m): the long side's
    # scale is where they become likelier than noise, between 2 and 4 σ
    onset = written.fusion["nlos_onset_m"]
    assert 0.06 < onset < 0.12 and "likelier NLOS than noise" in out, (onset, out)
    assert written.filter_config().robust.c_long == pytest.approx(onset / 0.1)
    # white noise only: no correlated part worth the multipath states is written
    assert "multipath_sigma_m" not in written.fusion and "(too small to write)" in out
    assert written.anchors_m == parse(base.read_text()).anchors_m
    assert model.phase_centre_m() == pytest.approx(PHASE_CENTRE_M, abs=0.01)
    assert model.log_distance_m == pytest.approx(LOG_DISTANCE_M, abs=0.015)
    assert "(range_model.log_distance_m)" in out
    delays = dict(model.anchor_delays_m)
    assert sorted(delays) == sorted(DELAYS)
    assert all(abs(delays[a] - DELAYS[a]) < 0.01 for a in DELAYS), delays
    checked = uwbd("check-config", "calibrated.toml", cwd=tmp_path)
    assert checked.returncode == 0, checked.stderr
    # the tag's term alone, for a robot whose anchors are other units
    alone = uwbd("calibrate-ranges", "calib.mcap", "--degree", "2", "--no-anchor-delays",
                 "-o", "tag.toml", cwd=tmp_path)
    assert alone.returncode == 0, alone.stderr
    tag_only = parse(BASE + (tmp_path / "tag.toml").read_text()).filter_config()
    assert tag_only.range_model.degree == 2 and tag_only.range_model.anchor_delays_m == ()
    assert tag_only.range_bias_states is True


def test_the_anchors_term_is_fitted_from_their_orientations_and_applied(tmp_path: Path) -> None:
    """A recording whose ranges carry an anchors' degree-1 term (the ray in each anchor's
    axes): ``--anchor-degree 1`` recovers it from the orientations ``uwbd import inrol``
    keeps, writes it, and the config gives the filter the term and every anchor's axes."""
    data = calibration_recording(tmp_path / "calib", anchor_term_m=(0.02, -0.04, 0.03))
    assert uwbd("import", "inrol", str(data), "-o", "calib.mcap", cwd=tmp_path).returncode == 0
    done = uwbd("calibrate-ranges", "calib.mcap", "--anchor-degree", "1", "-o", "rm.toml",
                cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "anchors' term, degree 1 (each anchor's axes)" in done.stdout
    base = BASE + "[anchors]\n" + "".join(
        f"{a} = {{ position_m = [{x}, {y}, {z}], orientation_xyzw = {list(ORIENTATIONS[a])} }}\n"
        for a, (x, y, z) in ANCHORS.items())
    model = parse(base + (tmp_path / "rm.toml").read_text()).filter_config().range_model
    assert model.anchor_degree == 1
    assert model.anchor_coefficients_m == pytest.approx((0.02, -0.04, 0.03), abs=0.01)
    for a, rows in model.anchor_axes:
        assert np.array(rows) == pytest.approx(axes_of(ORIENTATIONS[a]))
    # the term taken off a range: from anchor 2 (turned 90° about z) along the room's +x,
    # which is the anchor's -y: -c_1,-1 √3
    at = model.anchor_term_m([2, 1], np.array([ANCHORS[2], ANCHORS[1]], dtype=float),
                             np.array(ANCHORS[2]) + np.array([1.0, 0.0, 0.0]))
    assert at[0] == pytest.approx(-S3 * model.anchor_coefficients_m[0])
    # a config without the orientations: nothing to fit it from
    (tmp_path / "positions.toml").write_text(BASE + "[anchors]\n" + "".join(
        f"{a} = [{x}, {y}, {z}]\n" for a, (x, y, z) in ANCHORS.items()))
    one_line(uwbd("calibrate-ranges", "calib.mcap", "--anchor-degree", "1", "-c",
                  "positions.toml", cwd=tmp_path), 2, "have no orientation in the config",
             "orientation_xyzw")


def test_a_distance_term_is_written_only_where_the_ranges_have_one(tmp_path: Path) -> None:
    """Ranges without a distance term, or with one that shrinks with distance (no DW1000's:
    a truth out of scale): the fit says k ± σ and writes 0, which clears an earlier
    calibration's k from the config it is written into."""
    for k, root in ((0.0, "none"), (-0.1, "negative")):
        ds = load_inrol(calibration_recording(tmp_path / root, log_distance_m=k, seed=3))
        cal = calibrate(range_samples(ds.uwb, ds.anchors_m, ds.truth_t_ns, ds.truth_p_m,
                                      ds.truth_rotation, ds.lever_arm_m, IDENTITY3), 1)
        assert cal.keys()["range_model"]["log_distance_m"] == 0.0, cal.fit
        assert cal.distance_fit[0] == pytest.approx(k, abs=0.015)
        assert "m not written (0:" in cal.summary("x", ""), cal.summary("x", "")
        earlier = BASE + "[range_model]\nlog_distance_m = 0.12\n"
        assert parse(apply_overrides(earlier, cal.overrides("calib"))).filter_config() \
            .range_model.log_distance_m == 0.0


def test_the_distance_term_comes_off_every_range_from_the_first() -> None:
    """Simulated ranges that read ``0.15 ln(r / 1 m)`` long, as a DW1000's grow with the
    distance: without the term the filter is three times as far off and overconfident;
    with ``log_distance_m`` configured it is as good as on the clean ranges. The inversion
    itself is within 0.1 mm from 0 to 50 m."""
    d = np.concatenate([np.linspace(0.0, 0.1, 11), np.geomspace(0.1, 50.0, 300)])
    for k in (0.0, 0.12, 0.5):
        forward = d + k * np.log(np.maximum(d, 0.1))  # constant below 0.1 m
        assert RangeModel(log_distance_m=k).without_distance_term(forward) == \
            pytest.approx(d, abs=1e-4)
    short = handheld_async(3)
    sim = simulate(dataclasses.replace(short, segments=short.segments[:8]))  # 37 s
    cfg = parse(simulation_toml(sim)).filter_config()
    longer = [dataclasses.replace(f, ranges=tuple(
        dataclasses.replace(r, range_m=r.range_m + 0.15 * math.log(r.range_m))
        for r in f.ranges)) for f in sim.uwb]

    def accuracy(c: FilterConfig, uwb: list) -> object:
        poses, _, _ = run_filter(c, merge(sim.imu, uwb))
        return score_poses(poses, sim.truth_t_ns, sim.truth_p_m, 10.0)

    clean, left_in = accuracy(cfg, sim.uwb), accuracy(cfg, longer)
    taken_off = accuracy(dataclasses.replace(cfg, range_model=RangeModel(log_distance_m=0.15)),
                         longer)
    assert left_in.rmse_xy_m > 2.5 * clean.rmse_xy_m and left_in.nees_mean > 4, left_in
    assert taken_off.rmse_3d_m == pytest.approx(clean.rmse_3d_m, rel=0.02), (taken_off, clean)
    assert taken_off.nees_mean < 1.5, taken_off


def test_the_anchors_term_comes_off_every_range_at_the_prior_position() -> None:
    """Simulated ranges carrying an anchors' degree-1 term (the ray in each anchor's axes,
    each turned 90° more about z than the one before): left in, the filter is worse; taken
    off at the prior position, as good as on clean ranges."""
    short = handheld_async(3)
    sim = simulate(dataclasses.replace(short, segments=short.segments[:8]))  # 37 s
    cfg = parse(simulation_toml(sim)).filter_config()
    c = (0.02, -0.05, 0.04)
    anchors = np.array(sim.config.anchors_m)
    lever = np.array(sim.config.lever_arm_m)  # body z; the simulated body stays level
    axes = [axes_of((0.0, 0.0, math.sin(i * math.pi / 4), math.cos(i * math.pi / 4)))
            for i in range(len(anchors))]

    def carrying(f: UwbRanges) -> UwbRanges:
        antenna = np.array([np.interp(f.t_ns, sim.truth_t_ns, sim.truth_p_m[:, i])
                            for i in range(3)]) + lever
        out = []
        for r in f.ranges:
            ray = axes[r.anchor_id].T @ (antenna - anchors[r.anchor_id])
            term = float(np.array(c) @ basis(ray[None, :] / np.linalg.norm(ray), 1)[0])
            out.append(dataclasses.replace(r, range_m=r.range_m + term))
        return dataclasses.replace(f, ranges=tuple(out))

    uwb = [carrying(f) for f in sim.uwb]

    def accuracy(c_: FilterConfig, frames: list) -> object:
        poses, _, _ = run_filter(c_, merge(sim.imu, frames))
        return score_poses(poses, sim.truth_t_ns, sim.truth_p_m, 10.0)

    model = RangeModel(anchor_degree=1, anchor_coefficients_m=c, anchor_axes=tuple(
        (i, tuple(tuple(row) for row in C.tolist())) for i, C in enumerate(axes)))
    clean, left_in = accuracy(cfg, sim.uwb), accuracy(cfg, uwb)
    taken_off = accuracy(dataclasses.replace(cfg, range_model=model), uwb)
    assert left_in.rmse_3d_m > 1.5 * clean.rmse_3d_m, (left_in, clean)
    assert taken_off.rmse_3d_m < 1.1 * clean.rmse_3d_m, (taken_off, clean)


def test_a_correlated_range_error_is_measured_and_written_for_the_multipath_states(
        tmp_path: Path) -> None:
    """A recording whose ranges carry a Gauss–Markov error per anchor (0.06 m over 1.5 s)
    beside the white noise: calibrate-ranges writes it as fusion.multipath_sigma_m and
    multipath_tau_s, which the config then gives the filter."""
    ds = load_inrol(calibration_recording(tmp_path / "calib", correlated=(0.06, 1.5)))
    cal = calibrate(range_samples(ds.uwb, ds.anchors_m, ds.truth_t_ns, ds.truth_p_m,
                                  ds.truth_rotation, ds.lever_arm_m, IDENTITY3), 1)
    fusion = cal.keys()["fusion"]
    assert 0.04 < fusion["multipath_sigma_m"] < 0.08, cal.noise
    assert 1.0 < fusion["multipath_tau_s"] < 2.2, cal.noise
    cfg = parse(BASE + cal.snippet("calib")).filter_config()
    assert cfg.multipath_states and cfg.multipath_tau_s == fusion["multipath_tau_s"]


def test_the_nlos_tail_is_fitted_and_a_thin_one_sets_nothing() -> None:
    """Standardised residuals, a Gaussian core with an exponential long tail (share ε,
    scale 3 σ): the fit finds both, and the onset where ``(1 − ε) φ(t) = ε e^(−t/3)/3``;
    Gaussian residuals, or a tail of 0.5 %, set no onset (the default stays)."""
    rng = np.random.default_rng(1)
    for share, onset_sigma in ((0.1, 2.54), (0.2, 2.10)):
        k = int(share * 20000)
        z = np.concatenate([rng.normal(0, 1, 20000 - k), rng.exponential(3.0, k)])
        tail = nlos_tail(z, 0.1)
        assert tail.fraction == pytest.approx(share, abs=0.02)
        assert tail.scale_m == pytest.approx(0.3, abs=0.05)
        assert tail.onset_m == pytest.approx(onset_sigma * 0.1, abs=0.02)
    for share in (0.0, 0.005):
        k = int(share * 20000)
        z = np.concatenate([rng.normal(0, 1, 20000 - k), rng.exponential(3.0, k)])
        assert nlos_tail(z, 0.1).onset_m is None


def test_the_nlos_onset_sets_the_long_side_scale_and_is_checked() -> None:
    assert parse(BASE).filter_config().robust == RobustPolicy()
    cfg = parse(BASE + "[fusion]\nrange_sigma_m = 0.08\nnlos_onset_m = 0.12\n").filter_config()
    assert cfg.robust.c_long == pytest.approx(1.5) and cfg.robust.c_short == 4.0
    with pytest.raises(ConfigError) as err:
        parse(BASE + "[fusion]\nnlos_onset_m = -0.1\n", "robot.toml")
    assert "robot.toml: fusion.nlos_onset_m:" in str(err.value), str(err.value)


def test_calibrate_ranges_errors_are_one_line(tmp_path: Path) -> None:
    sim = tmp_path / "sim.mcap"
    assert uwbd("simulate", "-o", str(sim), "--duration", "5").returncode == 0
    one_line(uwbd("calibrate-ranges", str(sim), cwd=tmp_path), 2,
             "uwbd calibrate-ranges:", "ranges with truth over", "record about 90 s")
    one_line(uwbd("calibrate-ranges", "missing.mcap", cwd=tmp_path), 2,
             "cannot read missing.mcap")
    one_line(uwbd("calibrate-ranges", str(sim), "-o", "nowhere/rm.toml", cwd=tmp_path), 2,
             "folder nowhere does not exist")
    one_line(uwbd("calibrate-ranges", str(sim), "--write-config", str(sim), "out.toml",
                  cwd=tmp_path), 2, str(sim))
    flat = calibration_recording(tmp_path / "flat", seconds=35.0, attitude=False)
    assert uwbd("import", "inrol", str(flat), "-o", "flat.mcap", cwd=tmp_path).returncode == 0
    one_line(uwbd("calibrate-ranges", "flat.mcap", cwd=tmp_path), 2,
             "the ground truth has no orientation", "--degree 0 fits the anchors' delays")
    delays = uwbd("calibrate-ranges", "flat.mcap", "--degree", "0", cwd=tmp_path)
    assert delays.returncode == 0 and "anchor antenna delays" in delays.stdout, delays.stderr


def test_report_shows_the_range_residuals_raw_and_with_the_model(tmp_path: Path) -> None:
    assert uwbd("simulate", "-o", "s.mcap", "--duration", "20", cwd=tmp_path).returncode == 0
    plain = uwbd("report", "s.mcap", "-o", "plain", cwd=tmp_path)
    assert plain.returncode == 0, plain.stderr
    assert "robust σ" in plain.stdout and "(no [range_model]: uwbd calibrate-ranges" in plain.stdout
    assert (tmp_path / "plain" / "ranges.png").stat().st_size > 10_000
    modelled = uwbd("report", "s.mcap", "-o", "model", "--set",
                    "range_model.anchor_delays_m={ 0 = 0.05 }", cwd=tmp_path)
    assert modelled.returncode == 0, modelled.stderr
    line = next(t for t in modelled.stdout.splitlines() if t.startswith("  median per anchor"))
    raw, taken_off = (float(x) for x in line.split("0 ")[1].split(",")[0].split("/"))
    assert taken_off == pytest.approx(raw - 0.05, abs=1e-3)
    assert "m with the range model" in modelled.stdout
    assert (tmp_path / "model" / "ranges.png").stat().st_size > 10_000


def test_another_programs_log_of_the_same_topics_is_said_not_crashed_on(tmp_path: Path) -> None:
    with (tmp_path / "foreign.mcap").open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("x", "jsonschema", b"{}")
        for topic in ("/imu", "/uwb", "/truth"):
            channel = w.register_channel(topic, "json", schema)
            for k in range(5):
                w.add_message(channel, log_time=k * 10**9, publish_time=k * 10**9,
                              data=b'{"hello": %d}' % k)
        w.finish()
    for command in (("calibrate-ranges", "-c", str(tmp_path / "robot.toml")),
                    ("calibrate-imu",)):
        (tmp_path / "robot.toml").write_text(BASE)
        done = uwbd(command[0], "foreign.mcap", *command[1:], cwd=tmp_path)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert "internal error" not in done.stderr
        assert "5 of 5 /truth records are not poses and were skipped" in done.stderr
        assert done.stderr.splitlines()[-1].startswith(f"uwbd {command[0]}: foreign.mcap: no ")
