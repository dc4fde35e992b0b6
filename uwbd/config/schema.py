"""What each key may hold: the kinds of TOML value (said as ``expected {what}``), the bounds
of numbers, each section's keys, the drivers (UWB or IMU, the anchor ids they report), and
the limits the checks of the file as a whole hold it to."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.nlink import N_SLOTS
from uwbd.config.model import IMU_INTRINSIC_VECTORS, IMU_NOISE_KEYS
from uwbd.config.ros2 import DISTROS, MAX_DOMAIN_ID, NAMESPACE, NODE_NAME, TOPIC_KEYS, TOPIC_NAME
from uwbd.config.spelling import maybe, show, type_name
from uwbd.fusion.core.noise import ImuNoise
from uwbd.fusion.models.range_model import MAX_DEGREE
from uwbd.fusion.policy.installation import MAX_ANCHOR_COORD_M
from uwbd.fusion.settings import Mode


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_finite_vec(v: object, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n
            and all(_is_number(x) and math.isfinite(x) for x in v))


@dataclass(frozen=True)
class Kind:
    """A TOML value's expected type: said as ``expected {what}``."""

    what: str
    ok: Callable[[Any], bool]


BOOL = Kind("true or false", lambda v: isinstance(v, bool))
NUMBER = Kind("a number", _is_number)
INTEGER = Kind("an integer", lambda v: isinstance(v, int) and not isinstance(v, bool))
STRING = Kind("a string", lambda v: isinstance(v, str))
ENDPOINTS = Kind("an array of endpoint strings (\"tcp/192.168.1.10:7447\")",
                 lambda v: isinstance(v, list) and all(isinstance(e, str) for e in v))
VEC3 = Kind("[x, y, z] of finite numbers", lambda v: _is_finite_vec(v, 3))
XYZW = Kind("[qx, qy, qz, qw] of finite numbers", lambda v: _is_finite_vec(v, 4))
ROWS = Kind("3 rows of 3 finite numbers ([[1, 0, 0], [0, 1, 0], [0, 0, 1]])",
            lambda v: isinstance(v, list) and len(v) == 3 and all(_is_finite_vec(r, 3) for r in v))
NUMBERS = Kind("an array of finite numbers", lambda v: isinstance(v, list) and all(
    _is_number(x) and math.isfinite(x) for x in v))
DELAYS = Kind("a table of anchor id = delay in m ({ 1 = -0.12, 2 = 0.02 })",
               lambda v: isinstance(v, dict) and all(_is_number(x) and math.isfinite(x)
                                                     for x in v.values()))
PAIR = Kind("[lowest, highest] of finite numbers, in m", lambda v: _is_finite_vec(v, 2))


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ``lo < v`` (``lo <= v`` when closed), ``v <= hi`` likewise."""

    lo: float | None = 0.0
    hi: float | None = None
    lo_closed: bool = False
    hi_closed: bool = True

    def problem(self, v: float) -> str | None:
        if not math.isfinite(v):
            return f"must be a finite number, got {show(v)}"
        low_ok = self.lo is None or (v >= self.lo if self.lo_closed else v > self.lo)
        high_ok = self.hi is None or (v <= self.hi if self.hi_closed else v < self.hi)
        return None if low_ok and high_ok else f"must be {self.said()}, got {show(v)}"

    def said(self) -> str:
        parts = []
        if self.lo == 0:
            parts.append("zero or more" if self.lo_closed else "positive")
        elif self.lo is not None:
            parts.append(f"{'at least' if self.lo_closed else 'more than'} {_bound(self.lo)}")
        if self.hi is not None:
            parts.append(f"{'at most' if self.hi_closed else 'less than'} {_bound(self.hi)}")
        return " and ".join(parts)


def _bound(x: float) -> str:
    """A bound as a user typed it: 12000000, not 1.2e+07; 0.5 as 0.5."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


@dataclass(frozen=True)
class Key:
    kind: Kind
    bounds: Range | None = None
    choices: tuple[str, ...] = ()
    non_empty: bool = False

    def problem(self, value: Any) -> str | None:
        """What is wrong with ``value`` for this key, or ``None``."""
        if not self.kind.ok(value):
            return f"expected {self.kind.what}, got {show(value)} ({type_name(value)})"
        if isinstance(value, str) and "\0" in value:
            return f"{show(value)} holds a NUL character, which no path or name can"
        if isinstance(value, str) and len(value) > MAX_STRING_CHARS:
            return f"{len(value)} characters: at most {MAX_STRING_CHARS}"
        if self.bounds is not None:
            return self.bounds.problem(value)
        if self.choices and value not in self.choices:
            return f"expected one of {', '.join(self.choices)}, got {show(value)}" + maybe(
                value, self.choices)
        if self.non_empty and not value.strip():
            return "must not be empty"
        return None


MAX_STRING_CHARS = 4096  # a path's (PATH_MAX); names are shorter still (NAME)
MAX_NAME_CHARS = 64  # a robot's name: part of key expressions and of log files' names
# every number has bounds: past them a value is a slip (a unit, an exponent), not a setting
_SIGMA_M = Range(0.0, 100.0, lo_closed=True)  # a range error's σ, or a delay's
_LENGTH_M = Range(0.0, 1000.0)
MAX_BAUD = 12_000_000  # the fastest USB serial adapters (FTDI FT232H); the kernel's limit is near
SOURCE_SPEC = {"name": Key(STRING, non_empty=True), "driver": Key(STRING),
               "port": Key(STRING, non_empty=True), "baud": Key(INTEGER, Range(0.0, MAX_BAUD))}
_IMU_SPEC = {"mounting": Key(ROWS), "lever_arm_m": Key(VEC3),
             # noise densities: consumer MEMS parts are ~1e-3, tactical grade ~1e-5
             "acc_noise_mps2_rthz": Key(NUMBER, Range(1e-7, 10.0)),
             "gyro_noise_rps_rthz": Key(NUMBER, Range(1e-8, 1.0)),
             "acc_bias_walk_mps3_rthz": Key(NUMBER, Range(1e-9, 1.0)),
             "gyro_bias_walk_rps2_rthz": Key(NUMBER, Range(1e-10, 0.1)),
             # full scales: under 1 g an IMU at rest clips; FULL_SCALE_PLAUSIBLE warns nearer
             "acc_full_scale_mps2": Key(NUMBER, Range(9.0, 1e5, lo_closed=True)),
             "gyro_full_scale_rps": Key(NUMBER, Range(0.5, 1e4, lo_closed=True)),
             # each axis of these within INTRINSIC_BOUNDS (checks.check_imu, per element)
             **{k: Key(VEC3) for k in IMU_INTRINSIC_VECTORS},
             "gyro_deadband_rps": Key(NUMBER, Range(0.0, 0.1, lo_closed=True)),
             "gravity_mps2": Key(NUMBER, Range(9.7, 9.9, lo_closed=True))}
_FUSION_SPEC = {
    "mode": Key(STRING, choices=tuple(m.value for m in Mode)),
    "range_sigma_m": Key(NUMBER, Range(0.0, 5.0)),
    "range_bias_states": Key(BOOL),
    "range_bias_sigma_m": Key(NUMBER, _SIGMA_M),
    "tag_delay_sigma_m": Key(NUMBER, _SIGMA_M),
    "zupt": Key(BOOL), "nhc": Key(BOOL), "robust": Key(BOOL),
    "nlos_onset_m": Key(NUMBER, Range(0.0, 10.0)),
    "known_height_m": Key(NUMBER, Range(-MAX_ANCHOR_COORD_M, MAX_ANCHOR_COORD_M, True)),
    "gate_probability": Key(NUMBER, Range(0.5, 1.0, hi_closed=False)),
    "min_anchors": Key(INTEGER, Range(1, 64, lo_closed=True)),
    "max_range_m": Key(NUMBER, Range(0.1, 10000.0, lo_closed=True)),
    "multipath_sigma_m": Key(NUMBER, Range(0.0, 2.0, lo_closed=True)),
    "multipath_tau_s": Key(NUMBER, Range(0.0, 3600.0)),
    "tag_side": Key(STRING, choices=("auto", "below", "above")),
    "height_range_m": Key(PAIR),
    # a pose is healthy only while its protection levels, at this risk, are within these
    "integrity_risk": Key(NUMBER, Range(1e-9, 0.5)),
    "horizontal_alert_limit_m": Key(NUMBER, _LENGTH_M),
    "vertical_alert_limit_m": Key(NUMBER, _LENGTH_M),
    "height_needed": Key(BOOL),
    "range_bias_bound_m": Key(NUMBER, Range(0.0, 5.0, lo_closed=True)),
    "false_alert_probability": Key(NUMBER, Range(1e-12, 0.1)),
    # > 0: the lever arm's error estimated as states, with this prior σ per axis
    "lever_arm_sigma_m": Key(NUMBER, Range(0.0, 2.0, lo_closed=True)),
}
_PIPELINE_SPEC = {"aligner_wait_ms": Key(NUMBER, Range(0.0, 1000.0, lo_closed=True)),
                  "pose_rate_hz": Key(NUMBER, Range(0.1, 1000.0, lo_closed=True)),
                  "status_period_s": Key(NUMBER, Range(0.05, 3600.0, lo_closed=True)),
                  "stall_after_s": Key(NUMBER, Range(0.1, 3600.0, lo_closed=True))}
_LOG_SPEC = {"directory": Key(STRING, non_empty=True),
             "rotate_mb": Key(NUMBER, Range(0.1, 1e6, lo_closed=True)),
             "rotate_minutes": Key(NUMBER, Range(1.0, 1e6, lo_closed=True))}
_ZENOH_SPEC = {"enabled": Key(BOOL), "mode": Key(STRING, choices=("peer", "client", "router")),
               "connect": Key(ENDPOINTS), "listen": Key(ENDPOINTS), "prefix": Key(STRING),
               "config": Key(STRING, non_empty=True),
               "multicast_scouting": Key(BOOL)}
NAME = Kind(f"a name of letters, digits, '-' and '_', at most {MAX_NAME_CHARS} (\"robot1\")",
            lambda v: isinstance(v, str) and len(v) <= MAX_NAME_CHARS
            and re.fullmatch(r"[A-Za-z0-9_-]+", v) is not None)
FRAME_ID = Kind("a frame name of letters, digits, '_', '-', '.' and '/' (\"base_link\")",
                lambda v: isinstance(v, str)
                and re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_./-]*", v) is not None)
_ROBOT_SPEC = {"name": Key(NAME), "nav_frame_id": Key(FRAME_ID),
               "body_frame_id": Key(FRAME_ID)}
# the daemon's ROS 2 topics (uwbd.config.ros2: ROS 2's name rules)
ROS_NODE = Kind("a ROS 2 node name of letters, digits and '_', not starting with a digit "
                "(\"uwbd\")", lambda v: isinstance(v, str) and NODE_NAME.fullmatch(v) is not None)
ROS_NAMESPACE = Kind("a ROS 2 namespace (\"/robot1\", or \"/\" for none)",
                     lambda v: isinstance(v, str) and NAMESPACE.fullmatch(v) is not None)
ROS_TOPIC = Kind("a ROS 2 topic name (\"uwbd/pose\", \"/tf\", \"~/imu\"; \"\" turns it off)",
                 lambda v: isinstance(v, str) and (v == "" or TOPIC_NAME.fullmatch(v) is not None))
_ROS2_SPEC = {"enabled": Key(BOOL),
              "domain_id": Key(INTEGER, Range(0, MAX_DOMAIN_ID, lo_closed=True)),
              "namespace": Key(ROS_NAMESPACE), "node_name": Key(ROS_NODE),
              "distro": Key(STRING, choices=DISTROS),
              **{key: Key(ROS_TOPIC) for key in TOPIC_KEYS.values()}}
# the tag antenna's direction-dependent delay (uwbd.fusion.models.range_model), as
# `uwbd calibrate-ranges` writes it
_RANGE_MODEL_SPEC = {"tag_degree": Key(INTEGER, Range(0.0, MAX_DEGREE, lo_closed=True)),
                     "tag_coefficients_m": Key(NUMBERS), "tag_mounting": Key(ROWS),
                     "anchor_delays_m": Key(DELAYS), "calibrated_from": Key(STRING),
                     # k of k ln(d / 1 m): ~0.12 m measured; the delay grows with the
                     # distance (k ≥ 0), and beyond 0.5 m it is no antenna's
                     "log_distance_m": Key(NUMBER, Range(0.0, 0.5, lo_closed=True)),
                     # the anchors' own direction term: [anchors] entries with orientations
                     "anchor_degree": Key(INTEGER, Range(0.0, MAX_DEGREE, lo_closed=True)),
                     "anchor_coefficients_m": Key(NUMBERS)}
TABLES: dict[str, dict[str, Key]] = {
    "imu": _IMU_SPEC, "fusion": _FUSION_SPEC, "range_model": _RANGE_MODEL_SPEC,
    "pipeline": _PIPELINE_SPEC, "log": _LOG_SPEC, "zenoh": _ZENOH_SPEC, "robot": _ROBOT_SPEC,
    "ros2": _ROS2_SPEC}
SECTIONS = ("sources", "anchors", "imu", "fusion", "range_model", "pipeline", "log", "zenoh",
            "robot", "ros2")


def anchor_id(key: str) -> int | None:
    """The id an ``[anchors]`` key spells (``"3"``, ``"0x1151"``), or ``None``."""
    try:
        found = int(key, 0)
    except ValueError:
        return None
    return found if found >= 0 else None


@dataclass(frozen=True)
class Driver:
    """What a driver's device reports: UWB ranges or IMU samples; with anchor positions or
    not; which anchor ids."""

    uwb: bool
    anchor_positions: bool = False
    anchor_ids: range = range(0)
    ids_said: str = ""


DRIVERS = {
    "wit": Driver(uwb=False),
    # TagFrame0: a distance per slot 0..7, no positions (docs/wire-formats.md)
    "nlink": Driver(True, False, range(N_SLOTS), f"TagFrame0 slots 0..{N_SLOTS - 1}"),
    # shell `lec` and TLV 0x49: each range with the anchor's 16-bit short id and position
    "dwm1001": Driver(True, True, range(1 << 16), "16-bit short ids 0..0xFFFF"),
    "dwm1001-tlv": Driver(True, True, range(1 << 16), "16-bit short ids 0..0xFFFF"),
    # NodeFrame2: a record per remote node, by its node id, no positions (§3.3)
    "nlink-node2": Driver(True, False, range(256), "NodeFrame2 node ids 0..255"),
    # mc (trek1000) or mr (trek1000-raw) lines: ranges to anchors A0..A3, no positions (§4)
    "trek1000": Driver(True, False, range(4), "TREK1000 anchors A0..A3 as ids 0..3"),
    "trek1000-raw": Driver(True, False, range(4), "TREK1000 anchors A0..A3 as ids 0..3"),
}
UWB_DRIVERS = tuple(name for name, d in DRIVERS.items() if d.uwb)
IMU_DRIVERS = tuple(name for name, d in DRIVERS.items() if not d.uwb)
STANDARD_BAUDS = frozenset({
    1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000,
    921600, 1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000, 4000000})
MIN_ANCHOR_SPACING_M = 0.05
ROTATION_TOLERANCE = 1e-3  # |C Cᵀ - I|: typed-in rows (0.7071) pass and are re-orthonormalised
# a noise density this many times off its default is more likely a unit slip than a datasheet
NOISE_PLAUSIBLE_FACTOR = 100.0
NOISE_DEFAULTS = {key: getattr(ImuNoise(), name) for key, name in IMU_NOISE_KEYS.items()}
G_MPS2 = 9.80665
FULL_SCALE_PLAUSIBLE = {  # the smallest and largest ranges MEMS parts offer, with margin
    "acc_full_scale_mps2": (1.9 * G_MPS2, 70 * G_MPS2, "2 g", "64 g", "m/s²"),
    "gyro_full_scale_rps": (math.radians(120), math.radians(4100), "125 °/s", "4000 °/s",
                            "rad/s")}
# [imu] intrinsics, per axis: a MEMS part's gain is within a few % of 1, its zero-g offset
# within about 0.15 g, its zero-rate offset within about 20 °/s (datasheets, after soldering)
INTRINSIC_BOUNDS = {"acc_scale": Range(0.8, 1.2, lo_closed=True),
                    "acc_offset_mps2": Range(-2.0, 2.0, lo_closed=True),
                    "gyro_offset_rps": Range(-0.5, 0.5, lo_closed=True)}
GRAVITY_PLAUSIBLE_MPS2 = (9.77, 9.84)  # the Earth's surface: 9.78 (equator) .. 9.83 (poles)
DEADBAND_PLAUSIBLE_RPS = 0.02  # above this a dead-band loses slow turns (1.1 °/s)
# Zenoh 1.x link protocols (<protocol>/<address>[?<metadata>][#<config>])
ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial",
                   "vsock")
HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
HOSTNAME = re.compile(r"[A-Za-z0-9_](?:[A-Za-z0-9_.-]*[A-Za-z0-9_])?")
