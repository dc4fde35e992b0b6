"""The file as a whole: the :class:`Report` of problems and warnings, and the checks that
go beyond one key's type and range: sources (unique names and devices, a UWB one), anchors
(what the driver needs, apart, within 10 km), sigmas, the IMU (a proper mounting, plausible
noise and full scale), the range model, ROS 2's topic names, and last the filter itself;
the ``[zenoh]`` table's in :mod:`uwbd.config.zenoh_checks`."""

from __future__ import annotations

import math
import re
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from uwbd.config.model import Config, SourceConfig, Vec3, vec3
from uwbd.config.ros2 import TOPIC_KEYS, settings_of
from uwbd.config.schema import (
    DEADBAND_PLAUSIBLE_RPS,
    DRIVERS,
    FULL_SCALE_PLAUSIBLE,
    GRAVITY_PLAUSIBLE_MPS2,
    IMU_DRIVERS,
    INTRINSIC_BOUNDS,
    MIN_ANCHOR_SPACING_M,
    NOISE_DEFAULTS,
    NOISE_PLAUSIBLE_FACTOR,
    ROTATION_TOLERANCE,
    SECTIONS,
    STANDARD_BAUDS,
    UWB_DRIVERS,
    anchor_id,
)
from uwbd.config.spelling import show, toml_key
from uwbd.fusion.filter import Filter
from uwbd.fusion.models.range_model import n_coefficients
from uwbd.fusion.policy.fusing import MAX_RANGE_BIAS_SIGMA_M
from uwbd.fusion.policy.installation import MAX_ANCHOR_COORD_M
from uwbd.fusion.settings import IDENTITY3


class Report:
    """Problems and warnings, each ``"{where}: {key}: {what}"``."""

    def __init__(self, where: str) -> None:
        self.where = where
        self._errors: list[tuple[int, str]] = []
        self._warnings: list[tuple[int, str]] = []

    def error(self, key: str, what: str) -> None:
        self._errors.append((self._rank(key), f"{self.where}: {key}: {what}"))

    def warn(self, key: str, what: str) -> None:
        self._warnings.append((self._rank(key), f"{self.where}: {key}: {what}"))

    @property
    def errors(self) -> list[str]:
        """In the order of the sections (``[[sources]]`` first), each as found."""
        return [line for _, line in sorted(self._errors, key=lambda e: e[0])]

    @property
    def warnings(self) -> list[str]:
        return [line for _, line in sorted(self._warnings, key=lambda e: e[0])]

    @staticmethod
    def _rank(key: str) -> int:
        section = re.split(r"[.\[]", key, maxsplit=1)[0]
        return SECTIONS.index(section) + 1 if section in SECTIONS else 0


def mounting_rotation(r: Report, rows: list[list[float]] | None, key: str = "imu.mounting",
                      what: str = "sensor -> body") -> tuple[Vec3, Vec3, Vec3]:
    """``imu.mounting`` (or another ``key``'s rows) as a rotation; rows orthonormal only to a
    typed-in precision are replaced by the nearest rotation (the filter wants them exact)."""
    if rows is None:
        return IDENTITY3
    C = np.array(rows, dtype=float)
    off = float(np.abs(C @ C.T - np.eye(3)).max())
    det = float(np.linalg.det(C))
    if off > ROTATION_TOLERANCE or det < 0:
        r.error(key, "rows must be orthonormal with determinant +1 (a rotation "
                f"{what}), got det {det:.3f}"
                + (f", rows off orthonormal by up to {off:.3g}" if off > ROTATION_TOLERANCE
                   else ""))
        return IDENTITY3
    if not np.allclose(C @ C.T, np.eye(3), atol=1e-9, rtol=0.0):
        U, _, Vt = np.linalg.svd(C)
        C = U @ Vt
        r.warn(key, f"rows are orthonormal to {off:.1g} only: the nearest rotation "
               "is used")
    a, b, c = (vec3(row) for row in C.tolist())
    return (a, b, c)


def _is_device_path(port: str) -> bool:
    """A port that names a device (``simulated`` in a simulated log's config does not)."""
    return "/" in port or "\\" in port or re.fullmatch(r"(?i)com\d+", port) is not None


def check_sources(r: Report, sources: Sequence[tuple[int, SourceConfig]],
                  complete: bool) -> None:
    if not sources and complete:
        r.warn("sources", "none: enough to replay or import a log, not to `uwbd run`")
        return
    names: dict[str, int] = {}
    ports: dict[str, int] = {}
    for i, s in sources:
        if s.name in names:
            r.error(f"sources[{i}].name", f"{show(s.name)} is sources[{names[s.name]}]'s name "
                    "too: names must be unique")
        names.setdefault(s.name, i)
        if _is_device_path(s.port) and s.port in ports:
            r.error(f"sources[{i}].port", f"{show(s.port)} is sources[{ports[s.port]}]'s port "
                    "too: one device cannot feed two sources")
        ports.setdefault(s.port, i)
        if s.baud not in STANDARD_BAUDS:
            r.warn(f"sources[{i}].baud", f"{s.baud} is not a standard serial rate (115200, "
                   "230400, 460800, 921600, ...)")
    if not complete:
        return  # a source with a broken driver: what the file has in all is unknown
    drivers = {s.driver for _, s in sources}
    if not drivers & set(UWB_DRIVERS):
        r.error("sources", f"no UWB source (driver {', '.join(UWB_DRIVERS)})")
    elif not drivers & set(IMU_DRIVERS):
        r.warn("sources", f"no IMU source (driver {', '.join(IMU_DRIVERS)}): the filter needs "
               "IMU samples to start")


def check_anchors(r: Report, anchors: Mapping[int, Vec3], keys: Mapping[int, str],
                  complete: bool, sources: Sequence[tuple[int, SourceConfig]],
                  fusion: Mapping[str, Any]) -> None:
    def name(anchor_id: int) -> str:
        return f"anchors.{toml_key(keys[anchor_id])}"

    far = [a for a, p in anchors.items() if max(abs(x) for x in p) > MAX_ANCHOR_COORD_M]
    for a in far:
        r.error(name(a), f"{show(list(anchors[a]))}: more than {MAX_ANCHOR_COORD_M / 1000:g} "
                "km from the origin (metres in the site's ENU frame?)")
    ids = sorted(anchors)
    for k, a in enumerate(ids):
        for b in ids[:k]:
            d = math.dist(anchors[a], anchors[b])
            if d < MIN_ANCHOR_SPACING_M:
                r.error(name(a), f"{d:.3f} m from {name(b)}: anchors must be "
                        f"{MIN_ANCHOR_SPACING_M} m apart at least")
    if len(anchors) >= 3 and not far:
        points = np.array(list(anchors.values()))
        centred = points - points.mean(axis=0)
        direction = np.linalg.svd(centred)[2][0]
        off_line = centred - np.outer(centred @ direction, direction)
        if float(np.linalg.norm(off_line, axis=1).max()) < MIN_ANCHOR_SPACING_M:
            r.warn("anchors", "all on one line: the tag's position around that line is not "
                   "observable")
    uwb = [(i, s.driver) for i, s in sources if s.driver in DRIVERS and DRIVERS[s.driver].uwb]
    if not uwb:
        return  # for replay or import, or without UWB (an error of its own)
    for a in ids:
        if not any(a in DRIVERS[d].anchor_ids for _, d in uwb):
            said = "; ".join(f"{d} (sources[{i}]): {DRIVERS[d].ids_said}" for i, d in uwb)
            r.error(name(a), f"id {a} is not one the UWB source can report ({said})")
    ranges_only = [(i, d) for i, d in uwb if not DRIVERS[d].anchor_positions]
    if not ranges_only or not complete:
        return
    i, driver = ranges_only[0]
    if len(anchors) < 3:
        r.error("anchors", f"the {driver} driver (sources[{i}]) reports ranges only, so the "
                "anchor positions must be configured: 3 anchors at least (4 for a 3-D fix), "
                f"got {len(anchors)}")
    elif len(anchors) == 3 and "known_height_m" not in fusion:
        r.warn("anchors", "3 anchors give a 2-D fix only: add a 4th out of their plane, or "
               "set fusion.known_height_m")
    min_anchors = fusion.get("min_anchors", 1)
    if len(ranges_only) == len(uwb) and 3 <= len(anchors) < min_anchors:
        r.error("fusion.min_anchors", f"{min_anchors}, but only {len(anchors)} anchors are "
                f"configured (the {driver} driver ranges to configured anchors only)")


def check_fusion(r: Report, fusion: Mapping[str, Any], anchors: Mapping[int, Vec3]) -> None:
    if "height_range_m" in fusion:
        lo, hi = fusion["height_range_m"]
        if not lo < hi:
            r.error("fusion.height_range_m", f"expected [lowest, highest] in m, lowest < "
                    f"highest, got {show(fusion['height_range_m'])}")
    sigma = fusion.get("range_sigma_m", 0.1)
    if sigma > 1.0:
        r.warn("fusion.range_sigma_m", f"{sigma:g} m: UWB ranges are good to about 0.1 m; "
               "is it in metres?")
    for key in ("range_bias_sigma_m", "tag_delay_sigma_m"):
        if fusion.get(key, 0.0) > MAX_RANGE_BIAS_SIGMA_M:
            r.warn(f"fusion.{key}", f"{fusion[key]:g} m: the filter holds antenna-delay "
                   f"uncertainty to {MAX_RANGE_BIAS_SIGMA_M:g} m")
    if "max_range_m" in fusion and len(anchors) >= 2:
        spread = max(math.dist(p, q) for p in anchors.values() for q in anchors.values())
        if fusion["max_range_m"] < spread:
            r.warn("fusion.max_range_m", f"{fusion['max_range_m']:g} m, less than the "
                   f"{spread:.1f} m between the farthest anchors: ranges across the site "
                   "are dropped")


def check_ros2(r: Report, ros2: Mapping[str, Any], zenoh: Mapping[str, Any]) -> None:
    """The ROS 2 topics go out on the Zenoh session: not without one; two roles on one topic
    name would mix two types there."""
    if ros2.get("enabled", False) and not zenoh.get("enabled", True):
        r.error("ros2.enabled", "the ROS 2 topics go out over Zenoh, and zenoh.enabled is "
                "false: enable Zenoh, or turn ros2.enabled off")
    settings = settings_of(ros2, env={})
    seen: dict[str, str] = {}
    for role, name in settings.recorded.items():
        key = TOPIC_KEYS[role]
        if name in seen:
            r.error(f"ros2.{key}", f"{show(ros2.get(key, name))} is {name}, as "
                    f"ros2.{seen[name]} is: give each topic its own name")
        seen.setdefault(name, key)


MAX_TAG_TERM_M = 0.3  # an antenna's direction term is centimetres; more is not an antenna
MAX_ANCHOR_DELAY_M = 1.0  # a DW1000's uncalibrated antenna delay is ~0.3 m of range at most


def check_range_model(r: Report, model: dict[str, Any], fusion: Mapping[str, Any],
                      anchors: Mapping[int, Vec3], oriented: Collection[int] = ()) -> None:
    """``[range_model]``: as many coefficients as the degree takes, each plausible for an
    antenna; the tag's mounting a rotation (kept orthonormalised in the table); with the
    delay states off, every configured anchor's delay given."""
    delays = model.get("anchor_delays_m", {})
    for key, delay in delays.items():
        if anchor_id(key) is None:
            r.error(f"range_model.anchor_delays_m.{toml_key(key)}", "not an anchor id (an "
                    "integer of 0 or more: 3, 0x1151)")
        elif abs(delay) > MAX_ANCHOR_DELAY_M:
            r.error(f"range_model.anchor_delays_m.{toml_key(key)}", f"{delay:g} m: an antenna "
                    f"delay is at most {MAX_ANCHOR_DELAY_M:g} m (is it in metres?)")
    without = sorted(set(anchors) - {anchor_id(k) for k in delays})
    if delays and without and fusion.get("range_bias_states", True) is False:
        r.warn("range_model.anchor_delays_m", "no delay for anchor(s) "
               + ", ".join(map(str, without)) + " and fusion.range_bias_states = false: "
               "their ranges are taken with their antenna delay in them (calibrate-ranges "
               "on a recording that sees them, or the delay states back on)")
    _check_anchor_term(r, model, fusion, anchors, oriented)
    degree = model.get("tag_degree", 0)
    coefficients = model.get("tag_coefficients_m")
    if degree >= 2 and fusion.get("mode") == "loose":
        r.warn("range_model.tag_degree", f"{degree}: loose mode's fixes take degree 1 (the "
               "phase centre) only; the higher degrees apply to single ranges, in tight mode")
    if "tag_mounting" in model:
        model["tag_mounting"] = [list(row) for row in mounting_rotation(
            r, model["tag_mounting"], "range_model.tag_mounting", "tag axes -> body")]
    if degree == 0:
        if coefficients:
            r.error("range_model.tag_coefficients_m", "given without range_model.tag_degree: "
                    "set the degree they were fitted for (uwbd calibrate-ranges writes both)")
        return
    _check_coefficients(r, "range_model.tag_coefficients_m", "degree", degree, coefficients)


def _check_coefficients(r: Report, key: str, what: str, degree: int,
                        coefficients: list[float] | None) -> bool:
    """A direction term's coefficients: as many as ``degree`` takes, each plausible for an
    antenna; False when their number is wrong."""
    n = n_coefficients(degree)
    if coefficients is None or len(coefficients) != n:
        r.error(key, f"{what} {degree} takes {n} coefficients (degrees 1..{degree}, m = -l..l "
                "each), got " + ("none" if coefficients is None else str(len(coefficients))))
        return False
    big = [i for i, c in enumerate(coefficients) if abs(c) > MAX_TAG_TERM_M]
    if big:
        r.error(key, f"element {big[0]} is {coefficients[big[0]]:g} m: an antenna's direction "
                f"term is at most {MAX_TAG_TERM_M:g} m (are they in metres?)")
    return True


def check_imu(r: Report, imu: Mapping[str, Any], lever: Vec3) -> None:
    for key, default in NOISE_DEFAULTS.items():
        if key in imu and not (default / NOISE_PLAUSIBLE_FACTOR <= imu[key]
                               <= default * NOISE_PLAUSIBLE_FACTOR):
            r.warn(f"imu.{key}", f"{imu[key]:g} is more than {NOISE_PLAUSIBLE_FACTOR:g}x off "
                   f"the default {default:g}: is it in the unit of the key's key?")
    for key, (lo, hi, lo_said, hi_said, unit) in FULL_SCALE_PLAUSIBLE.items():
        if key in imu and not lo <= imu[key] <= hi:
            r.warn(f"imu.{key}", f"{imu[key]:g} {unit} is outside {lo_said}..{hi_said}: is it "
                   f"in {unit}?")
    if math.hypot(*lever) > 10.0:
        r.warn("imu.lever_arm_m", f"{math.hypot(*lever):.1f} m from the IMU to the antenna")
    _check_intrinsics(r, imu)


def _check_intrinsics(r: Report, imu: Mapping[str, Any]) -> None:
    """Each axis of the scale and offsets within what a MEMS part can be off by (an error
    naming the element: a unit slip, a capture that was not static, or the other sign
    convention); gravity where the Earth's surface has it; a dead-band that loses turns."""
    for key, bounds in INTRINSIC_BOUNDS.items():
        for k, v in enumerate(imu.get(key, ())):
            problem = bounds.problem(v)
            if problem is not None:
                r.error(f"imu.{key}[{k}]", problem + ("" if key != "acc_scale" else
                        " (a gain: reading per true m/s², 1 for a perfect sensor)"))
    lo, hi = GRAVITY_PLAUSIBLE_MPS2
    g = imu.get("gravity_mps2")
    if g is not None and not lo <= g <= hi:
        r.warn("imu.gravity_mps2", f"{g:g} m/s² is outside {lo:g}..{hi:g}, gravity at the "
               "Earth's surface (9.78 at the equator, 9.83 at the poles)")
    band = imu.get("gyro_deadband_rps", 0.0)
    if band > DEADBAND_PLAUSIBLE_RPS:
        r.warn("imu.gyro_deadband_rps", f"{band:g} rad/s ({math.degrees(band):.1f} °/s): turns "
               "slower than that are not seen at all (0, the default, leaves the gyro bias "
               "to the filter)")


_FILTER_NAMES = {  # FilterConfig field (or word) in a filter error -> the config's key
    "mounting_rotation": "imu.mounting", "lever_arm_m": "imu.lever_arm_m",
    "min_anchors": "fusion.min_anchors", "max_range_m": "fusion.max_range_m",
    "min_range_m": "fusion.max_range_m", "gate probability": "fusion.gate_probability",
    "tag side": "fusion.tag_side", "height_range_m": "fusion.height_range_m",
}
_FILTER_WORDS = re.compile("|".join(re.escape(w) for w in _FILTER_NAMES))


def check_filter(r: Report, config: Config) -> None:
    """A last net: what only the filter understands."""
    try:
        Filter(config.filter_config())
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        found = _FILTER_WORDS.search(text)
        r.error(_FILTER_NAMES[found.group()] if found else "fusion",
                "the filter cannot use it: "
                + _FILTER_WORDS.sub(lambda m: _FILTER_NAMES[m.group()], text))


def _check_anchor_term(r: Report, model: Mapping[str, Any], fusion: Mapping[str, Any],
                       anchors: Mapping[int, Vec3], oriented: Collection[int]) -> None:
    """``anchor_degree`` and its coefficients as the tag's; the anchors it cannot apply to
    (no orientation in ``[anchors]``), and loose mode (whose fixes take none), said."""
    degree = model.get("anchor_degree", 0)
    coefficients = model.get("anchor_coefficients_m")
    if degree == 0:
        if coefficients:
            r.error("range_model.anchor_coefficients_m", "given without "
                    "range_model.anchor_degree: set the degree they were fitted for (uwbd "
                    "calibrate-ranges writes both)")
        return
    if not _check_coefficients(r, "range_model.anchor_coefficients_m", "anchor degree",
                               degree, coefficients):
        return
    if fusion.get("mode") == "loose":
        r.warn("range_model.anchor_degree", f"{degree}: loose mode's fixes take no anchors' "
               "term (it applies to the ranges of tight mode)")
    without = sorted(set(anchors) - set(oriented))
    if not oriented:
        r.warn("range_model.anchor_degree", "no anchor in [anchors] has an orientation: the "
               "anchors' term applies to none (give them as { position_m = [x, y, z], "
               "orientation_xyzw = [qx, qy, qz, qw] })")
    elif without:
        r.warn("range_model.anchor_degree", "no orientation for anchor(s) "
               + ", ".join(map(str, without)) + ": their ranges take no anchor term (give "
               "them as { position_m = [x, y, z], orientation_xyzw = [qx, qy, qz, qw] })")
