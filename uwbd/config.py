"""uwbd's TOML configuration, validated into typed objects.

:func:`parse` checks the whole file and reports every problem at once: one
:class:`ConfigError` whose ``problems`` are lines ``"{file}: {key}: {what}"``, the key spelt
as in the TOML (``sources[1].port``, ``fusion.range_sigma_m``, ``anchors.3``,
``zenoh.listen[0]``), type errors with the type expected (``fusion.zupt: expected true or
false, got "yes" (a string)``). Unknown keys are errors too, since a misspelt option that is
silently ignored is worse than none. What is only suspicious (a non-standard baud rate, a
noise density 100x off its default, exactly 3 anchors) lands in ``Config.warnings``.
Sections::

    [[sources]]          name, driver, port, baud
    [anchors]            "<id>" = [x, y, z]            (m, navigation frame ENU)
    [imu]                mounting = 3x3 rows (sensor -> body FLU), lever_arm_m = [x, y, z],
                         noise densities from the IMU's datasheet (defaults: a consumer MEMS
                         part with margin for vibration): acc_noise_mps2_rthz (0.01),
                         gyro_noise_rps_rthz (0.001), acc_bias_walk_mps3_rthz (0.001),
                         gyro_bias_walk_rps2_rthz (0.0001); the full scale the sensor is set
                         to: acc_full_scale_mps2 (16 g), gyro_full_scale_rps (2000 °/s)
    [fusion]             mode, range_sigma_m, range_bias_states, range_bias_sigma_m (0.1:
                         each anchor's antenna delay), tag_delay_sigma_m (0.2: the tag's),
                         zupt, nhc, known_height_m, gate_probability, min_anchors, max_range_m,
                         robust (true: NLOS de-weighted), multipath_sigma_m (0.07; 0: off) and
                         multipath_tau_s (1): time-correlated range error per anchor,
                         tag_side ("auto", "below", "above" a plane of anchors),
                         height_range_m ([lo, hi]: where the tag can be, a mirror hint)
    [pipeline]           aligner_wait_ms (0), pose_rate_hz (50), status_period_s (1)
    [log]                directory ("logs"), rotate_mb (256), rotate_minutes (60)
    [zenoh]              enabled (true), mode ("peer"), connect [], listen [], prefix
                         ("uwbd/<hostname>"), multicast_scouting (true)

Beyond types and ranges (see the tables below), the file must make sense as a whole: with
sources, one of them is UWB; a driver that reports ranges only (``nlink``) needs 3 anchors
or more with ids it can report; anchors lie apart, within 10 km; Zenoh endpoints parse (and
Zenoh itself accepts them); ``imu.mounting`` is a rotation. A config without sources is one
for replaying or importing logs. :func:`apply_overrides` sets keys from the command line
(``fusion.zupt=false``) and returns the TOML actually used.
"""

from __future__ import annotations

import datetime
import difflib
import ipaddress
import json
import math
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers import PARSERS
from drivers.nlink import N_SLOTS
from uwbd.fusion.eskf import ImuNoise
from uwbd.fusion.filter import MAX_ANCHOR_COORD_M, MAX_RANGE_BIAS_SIGMA_M, Filter
from uwbd.fusion.gating import GatingPolicy
from uwbd.fusion.imu_check import ImuLimits
from uwbd.fusion.robust import RobustPolicy
from uwbd.fusion.settings import IDENTITY3, FilterConfig, Mode

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Vec3 = tuple[float, float, float]
MAX_CONFIG_BYTES = 1 << 20  # a config file is a few kB: more is some other file


class ConfigError(ValueError):
    """Configuration problems, each a line ``"{file}: {key}: {what}"``.

    ``problems`` lists them all; ``str()`` is them joined by newlines, so it starts with the
    first. ``warnings`` holds what was only suspicious in the same file."""

    def __init__(self, problems: str | Sequence[str], warnings: Sequence[str] = ()) -> None:
        self.problems: list[str] = [problems] if isinstance(problems, str) else list(problems)
        self.warnings: list[str] = list(warnings)
        super().__init__("\n".join(self.problems))


@dataclass(frozen=True)
class SourceConfig:
    name: str
    driver: str
    port: str
    baud: int = 115200


@dataclass(frozen=True)
class Config:
    sources: tuple[SourceConfig, ...] = ()
    anchors_m: dict[int, Vec3] = field(default_factory=dict)
    mounting: tuple[Vec3, Vec3, Vec3] = IDENTITY3
    lever_arm_m: Vec3 = (0.0, 0.0, 0.0)
    imu_noise: dict[str, float] = field(default_factory=dict)  # [imu] noise keys given
    imu_limits: dict[str, float] = field(default_factory=dict)  # [imu] full-scale keys given
    fusion: dict[str, Any] = field(default_factory=dict)
    pipeline: dict[str, Any] = field(default_factory=dict)
    log: dict[str, Any] = field(default_factory=dict)
    zenoh: dict[str, Any] = field(default_factory=dict)
    text: str = ""  # the TOML as read, for the log
    warnings: tuple[str, ...] = ()  # "{file}: {key}: {what}", suspicious but not wrong

    @property
    def aligner_wait_ns(self) -> int:
        return int(self.pipeline.get("aligner_wait_ms", 0) * 1_000_000)

    @property
    def pose_period_ns(self) -> int:
        return int(1e9 / self.pipeline.get("pose_rate_hz", 50))

    @property
    def status_period_ns(self) -> int:
        return int(self.pipeline.get("status_period_s", 1.0) * 1e9)

    def filter_config(self) -> FilterConfig:
        f = self.fusion
        return FilterConfig(
            mode=Mode(f.get("mode", "tight")), anchors_m=self.anchors_m,
            mounting_rotation=self.mounting, lever_arm_m=self.lever_arm_m,
            range_sigma_m=f.get("range_sigma_m", 0.10),
            range_bias_states=f.get("range_bias_states", True),
            range_bias_sigma_m=f.get("range_bias_sigma_m", 0.1),
            tag_delay_sigma_m=f.get("tag_delay_sigma_m", 0.2),
            imu_noise=ImuNoise(**{IMU_NOISE_KEYS[k]: v for k, v in self.imu_noise.items()}),
            imu_limits=ImuLimits(
                acc_full_scale_mps2=self.imu_limits.get("acc_full_scale_mps2",
                                                        ImuLimits.acc_full_scale_mps2),
                gyro_full_scale_rps=self.imu_limits.get("gyro_full_scale_rps",
                                                        ImuLimits.gyro_full_scale_rps)),
            robust=RobustPolicy(enabled=f.get("robust", True)),
            multipath_states=f.get("multipath_sigma_m", MULTIPATH_SIGMA_M) > 0,
            multipath_sigma_m=f.get("multipath_sigma_m", MULTIPATH_SIGMA_M) or MULTIPATH_SIGMA_M,
            multipath_tau_s=f.get("multipath_tau_s", 1.0),
            tag_side=f.get("tag_side", "auto"),
            height_range_m=((float(f["height_range_m"][0]), float(f["height_range_m"][1]))
                            if "height_range_m" in f else None),
            zupt=f.get("zupt", True),
            nhc=f.get("nhc", False), known_height_m=f.get("known_height_m"),
            gate_probability=f.get("gate_probability", 0.997),
            gating=GatingPolicy(min_anchors=f.get("min_anchors", 1),
                                max_range_m=f.get("max_range_m", 100.0)),
        )


# -- what each key may hold ----------------------------------------------------------------

def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_finite_vec(v: object, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n
            and all(_is_number(x) and math.isfinite(x) for x in v))


@dataclass(frozen=True)
class _Kind:
    """A TOML value's expected type: said as ``expected {what}``."""

    what: str
    ok: Callable[[Any], bool]


_BOOL = _Kind("true or false", lambda v: isinstance(v, bool))
_NUMBER = _Kind("a number", _is_number)
_INTEGER = _Kind("an integer", lambda v: isinstance(v, int) and not isinstance(v, bool))
_STRING = _Kind("a string", lambda v: isinstance(v, str))
_POSITIVE = _Kind("a positive number",
                  lambda v: _is_number(v) and math.isfinite(v) and v > 0)
_ENDPOINTS = _Kind("an array of endpoint strings (\"tcp/192.168.1.10:7447\")",
                   lambda v: isinstance(v, list) and all(isinstance(e, str) for e in v))
_VEC3 = _Kind("[x, y, z] of finite numbers", lambda v: _is_finite_vec(v, 3))
_ROWS = _Kind("3 rows of 3 finite numbers ([[1, 0, 0], [0, 1, 0], [0, 0, 1]])",
              lambda v: isinstance(v, list) and len(v) == 3
              and all(_is_finite_vec(r, 3) for r in v))
_PAIR = _Kind("[lowest, highest] of finite numbers, in m", lambda v: _is_finite_vec(v, 2))


@dataclass(frozen=True)
class _Range:
    """Bounds of a number: ``lo < v`` (``lo <= v`` when closed), ``v <= hi`` likewise."""

    lo: float | None = 0.0
    hi: float | None = None
    lo_closed: bool = False
    hi_closed: bool = True

    def problem(self, v: float) -> str | None:
        if not math.isfinite(v):
            return f"must be a finite number, got {_show(v)}"
        low_ok = self.lo is None or (v >= self.lo if self.lo_closed else v > self.lo)
        high_ok = self.hi is None or (v <= self.hi if self.hi_closed else v < self.hi)
        return None if low_ok and high_ok else f"must be {self.said()}, got {_show(v)}"

    def said(self) -> str:
        parts = []
        if self.lo == 0:
            parts.append("zero or more" if self.lo_closed else "positive")
        elif self.lo is not None:
            parts.append(f"{'at least' if self.lo_closed else 'more than'} {self.lo:g}")
        if self.hi is not None:
            parts.append(f"{'at most' if self.hi_closed else 'less than'} {self.hi:g}")
        return " and ".join(parts)


@dataclass(frozen=True)
class _Key:
    kind: _Kind
    bounds: _Range | None = None
    choices: tuple[str, ...] = ()
    non_empty: bool = False

    def problem(self, value: Any) -> str | None:
        """What is wrong with ``value`` for this key, or ``None``."""
        if not self.kind.ok(value):
            return f"expected {self.kind.what}, got {_show(value)} ({_type_name(value)})"
        if self.bounds is not None:
            return self.bounds.problem(value)
        if self.choices and value not in self.choices:
            return f"expected one of {', '.join(self.choices)}, got {_show(value)}" + _maybe(
                value, self.choices)
        if self.non_empty and not value.strip():
            return "must not be empty"
        return None


_ZERO_OR_MORE = _Range(0.0, lo_closed=True)
_POSITIVE_RANGE = _Range(0.0)
# [imu] key -> ImuNoise field
IMU_NOISE_KEYS = {"acc_noise_mps2_rthz": "acc", "gyro_noise_rps_rthz": "gyro",
                  "acc_bias_walk_mps3_rthz": "acc_bias", "gyro_bias_walk_rps2_rthz": "gyro_bias"}
IMU_LIMIT_KEYS = ("acc_full_scale_mps2", "gyro_full_scale_rps")  # ImuLimits fields
MULTIPATH_SIGMA_M = 0.07  # the default time-correlated range error (real installations)
_SOURCE_SPEC = {"name": _Key(_STRING, non_empty=True), "driver": _Key(_STRING),
                "port": _Key(_STRING, non_empty=True), "baud": _Key(_INTEGER, _POSITIVE_RANGE)}
_IMU_SPEC = {"mounting": _Key(_ROWS), "lever_arm_m": _Key(_VEC3),
             **{k: _Key(_POSITIVE) for k in (*IMU_NOISE_KEYS, *IMU_LIMIT_KEYS)}}
_FUSION_SPEC = {
    "mode": _Key(_STRING, choices=tuple(m.value for m in Mode)),
    "range_sigma_m": _Key(_NUMBER, _Range(0.0, 5.0)),
    "range_bias_states": _Key(_BOOL),
    "range_bias_sigma_m": _Key(_NUMBER, _ZERO_OR_MORE),
    "tag_delay_sigma_m": _Key(_NUMBER, _ZERO_OR_MORE),
    "zupt": _Key(_BOOL), "nhc": _Key(_BOOL), "robust": _Key(_BOOL),
    "known_height_m": _Key(_NUMBER, _Range(-MAX_ANCHOR_COORD_M, MAX_ANCHOR_COORD_M, True)),
    "gate_probability": _Key(_NUMBER, _Range(0.5, 1.0, hi_closed=False)),
    "min_anchors": _Key(_INTEGER, _Range(1, lo_closed=True)),
    "max_range_m": _Key(_NUMBER, _POSITIVE_RANGE),
    "multipath_sigma_m": _Key(_NUMBER, _ZERO_OR_MORE),
    "multipath_tau_s": _Key(_NUMBER, _POSITIVE_RANGE),
    "tag_side": _Key(_STRING, choices=("auto", "below", "above")),
    "height_range_m": _Key(_PAIR),
}
_PIPELINE_SPEC = {"aligner_wait_ms": _Key(_NUMBER, _Range(0.0, 1000.0, lo_closed=True)),
                  "pose_rate_hz": _Key(_NUMBER, _Range(0.0, 1000.0)),
                  "status_period_s": _Key(_NUMBER, _Range(0.05, 3600.0, lo_closed=True))}
_LOG_SPEC = {"directory": _Key(_STRING, non_empty=True),
             "rotate_mb": _Key(_NUMBER, _POSITIVE_RANGE),
             "rotate_minutes": _Key(_NUMBER, _POSITIVE_RANGE)}
_ZENOH_SPEC = {"enabled": _Key(_BOOL), "mode": _Key(_STRING, choices=("peer", "client", "router")),
               "connect": _Key(_ENDPOINTS), "listen": _Key(_ENDPOINTS), "prefix": _Key(_STRING),
               "multicast_scouting": _Key(_BOOL)}
_TABLES: dict[str, dict[str, _Key]] = {
    "imu": _IMU_SPEC, "fusion": _FUSION_SPEC, "pipeline": _PIPELINE_SPEC, "log": _LOG_SPEC,
    "zenoh": _ZENOH_SPEC}
_SECTIONS = ("sources", "anchors", "imu", "fusion", "pipeline", "log", "zenoh")


@dataclass(frozen=True)
class _Driver:
    """What a driver's device reports: UWB ranges or IMU samples; with anchor positions or
    not; which anchor ids."""

    uwb: bool
    anchor_positions: bool = False
    anchor_ids: range = range(0)
    ids_said: str = ""


_DRIVERS = {
    "wit": _Driver(uwb=False),
    # TagFrame0: a distance per slot 0..7, no positions (WIRE_FORMATS.md §3.2)
    "nlink": _Driver(True, False, range(N_SLOTS), f"TagFrame0 slots 0..{N_SLOTS - 1}"),
    # shell `lec` and TLV 0x49: each range with the anchor's 16-bit short id and position
    "dwm1001": _Driver(True, True, range(1 << 16), "16-bit short ids 0..0xFFFF"),
    "dwm1001-tlv": _Driver(True, True, range(1 << 16), "16-bit short ids 0..0xFFFF"),
}
UWB_DRIVERS = tuple(name for name, d in _DRIVERS.items() if d.uwb)
IMU_DRIVERS = tuple(name for name, d in _DRIVERS.items() if not d.uwb)
STANDARD_BAUDS = frozenset({
    1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000,
    921600, 1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000, 4000000})
MIN_ANCHOR_SPACING_M = 0.05
ROTATION_TOLERANCE = 1e-3  # |C Cᵀ - I|: typed-in rows (0.7071) pass and are re-orthonormalised
# a noise density this many times off its default is more likely a unit slip than a datasheet
NOISE_PLAUSIBLE_FACTOR = 100.0
_NOISE_DEFAULTS = {key: getattr(ImuNoise(), name) for key, name in IMU_NOISE_KEYS.items()}
G_MPS2 = 9.80665
_FULL_SCALE_PLAUSIBLE = {  # the smallest and largest ranges MEMS parts offer, with margin
    "acc_full_scale_mps2": (1.9 * G_MPS2, 70 * G_MPS2, "2 g", "64 g", "m/s²"),
    "gyro_full_scale_rps": (math.radians(120), math.radians(4100), "125 °/s", "4000 °/s",
                            "rad/s")}
# Zenoh 1.x link protocols (<protocol>/<address>[?<metadata>][#<config>])
ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial",
                   "vsock")
_HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_HOSTNAME = re.compile(r"[A-Za-z0-9_](?:[A-Za-z0-9_.-]*[A-Za-z0-9_])?")


# -- reading -------------------------------------------------------------------------------

def load(path: Path, overrides: Sequence[str] = ()) -> Config:
    """The config file at ``path`` with ``overrides`` (``section.key=value``) applied."""
    where = str(path)
    try:
        with path.open("rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as err:
        raise ConfigError(f"{where}: {err.strerror or err}") from err
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{where}: larger than {MAX_CONFIG_BYTES >> 20} MiB: not a config file")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{where}: not a UTF-8 text file (byte 0x{data[err.start]:02x} at "
                          f"offset {err.start})") from err
    if "\0" in text:
        raise ConfigError(f"{where}: not a text file (it holds NUL bytes)")
    # as Path.read_text did: universal newlines, and no byte-order mark
    text = text.removeprefix("\ufeff").replace("\r\n", "\n").replace("\r", "\n")
    if overrides:
        text = apply_overrides(text, overrides, where)
    return parse(text, where)


class _Report:
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
        return _SECTIONS.index(section) + 1 if section in _SECTIONS else 0


def parse(text: str, where: str = "<config>") -> Config:
    """The config in ``text`` (``where``: the file, for messages), every problem at once."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{where}: {err}") from err
    r = _Report(where)
    _unknown_keys(r, doc, _SECTIONS, "")
    sources, sources_complete = _sources(r, doc)
    anchors, anchor_keys, anchors_complete = _anchors(r, doc)
    tables = {name: _table(r, doc, name, spec) for name, spec in _TABLES.items()}
    imu, fusion, zenoh = tables["imu"], tables["fusion"], tables["zenoh"]
    mounting = _mounting(r, imu.get("mounting"))
    lever = _vec3(imu.get("lever_arm_m", [0.0, 0.0, 0.0]))
    _check_sources(r, sources, sources_complete)
    _check_anchors(r, anchors, anchor_keys, anchors_complete, sources, fusion)
    _check_fusion(r, fusion, anchors)
    _check_imu(r, imu, lever)
    _check_zenoh(r, zenoh)
    if r.errors:
        raise ConfigError(r.errors, r.warnings)
    config = Config(
        sources=tuple(s for _, s in sources), anchors_m=anchors, mounting=mounting,
        lever_arm_m=lever,
        imu_noise={k: float(imu[k]) for k in IMU_NOISE_KEYS if k in imu},
        imu_limits={k: float(imu[k]) for k in IMU_LIMIT_KEYS if k in imu},
        fusion=fusion, pipeline=tables["pipeline"], log=tables["log"], zenoh=zenoh, text=text,
        warnings=tuple(r.warnings))
    _check_filter(r, config)  # a last net: what only the filter understands
    if r.errors:
        raise ConfigError(r.errors, r.warnings)
    return config


def _unknown_keys(r: _Report, table: Mapping[str, Any], known: Sequence[str], prefix: str) -> None:
    for key in table:
        if key not in known:
            r.error(prefix + _key(key), "unknown key" + _known(key, sorted(known)))


def _table(r: _Report, doc: Mapping[str, Any], name: str, spec: Mapping[str, _Key]
           ) -> dict[str, Any]:
    """The section ``name``, its keys checked against ``spec``: only the valid ones kept."""
    table = doc.get(name, {})
    if not isinstance(table, dict):
        r.error(name, f"expected a table ([{name}]), got {_show(table)} ({_type_name(table)})")
        return {}
    _unknown_keys(r, table, tuple(spec), f"{name}.")
    good = {}
    for key, value in table.items():
        if key not in spec:
            continue
        problem = spec[key].problem(value)
        if problem is None:
            good[key] = value
        else:
            r.error(f"{name}.{_key(key)}", problem)
    return good


def _sources(r: _Report, doc: Mapping[str, Any]) -> tuple[list[tuple[int, SourceConfig]], bool]:
    """The valid ``[[sources]]`` with their index, and whether all were."""
    entries = doc.get("sources", [])
    if not isinstance(entries, list):
        r.error("sources", f"expected an array of tables ([[sources]]), got {_show(entries)} "
                           f"({_type_name(entries)})")
        return [], False
    out = []
    complete = True
    for i, s in enumerate(entries):
        key = f"sources[{i}]"
        if not isinstance(s, dict):
            r.error(key, f"expected a table ([[sources]]), got {_show(s)} ({_type_name(s)})")
            complete = False
            continue
        _unknown_keys(r, s, tuple(_SOURCE_SPEC), f"{key}.")
        ok = True
        for name, spec in _SOURCE_SPEC.items():
            if name not in s:
                if name != "baud":
                    r.error(f"{key}.{name}", f"required: {spec.kind.what}")
                    ok = False
                continue
            problem = spec.problem(s[name])
            if problem is None and name == "driver" and s[name] not in PARSERS:
                problem = f"unknown driver {_show(s[name])}" + _known(s[name], list(PARSERS))
            if problem is not None:
                r.error(f"{key}.{name}", problem)
                ok = False
        if ok:
            out.append((i, SourceConfig(s["name"], s["driver"], s["port"],
                                        s.get("baud", 115200))))
        complete = complete and ok
    return out, complete


def _anchors(r: _Report, doc: Mapping[str, Any]) -> tuple[dict[int, Vec3], dict[int, str], bool]:
    """The valid anchors, their keys as spelt in the file, and whether all were valid."""
    table = doc.get("anchors", {})
    if not isinstance(table, dict):
        r.error("anchors", f"expected a table ([anchors]), got {_show(table)} "
                           f"({_type_name(table)})")
        return {}, {}, False
    anchors: dict[int, Vec3] = {}
    keys: dict[int, str] = {}
    complete = True
    for key, value in table.items():
        name = f"anchors.{_key(key)}"
        anchor_id = _anchor_id(key)
        if anchor_id is None:
            r.error(name, "not an integer id (\"3\", \"0x1151\") of 0 or more")
            complete = False
            continue
        if not _VEC3.ok(value):
            r.error(name, f"expected {_VEC3.what}, got {_show(value)} ({_type_name(value)})")
            complete = False
            continue
        if anchor_id in keys:
            r.error(name, f"the same id as anchors.{_key(keys[anchor_id])}")
            complete = False
            continue
        anchors[anchor_id], keys[anchor_id] = _vec3(value), key
    return anchors, keys, complete


def _anchor_id(key: str) -> int | None:
    try:
        anchor_id = int(key, 0)
    except ValueError:
        return None
    return anchor_id if anchor_id >= 0 else None


def _vec3(value: Sequence[float]) -> Vec3:
    return (float(value[0]), float(value[1]), float(value[2]))


def _mounting(r: _Report, rows: list[list[float]] | None) -> tuple[Vec3, Vec3, Vec3]:
    """``imu.mounting`` as a rotation; rows orthonormal only to a typed-in precision are
    replaced by the nearest rotation (the filter wants them exact)."""
    if rows is None:
        return IDENTITY3
    C = np.array(rows, dtype=float)
    off = float(np.abs(C @ C.T - np.eye(3)).max())
    det = float(np.linalg.det(C))
    if off > ROTATION_TOLERANCE or det < 0:
        r.error("imu.mounting", "rows must be orthonormal with determinant +1 (a rotation "
                f"sensor -> body), got det {det:.3f}"
                + (f", rows off orthonormal by up to {off:.3g}" if off > ROTATION_TOLERANCE
                   else ""))
        return IDENTITY3
    if not np.allclose(C @ C.T, np.eye(3), atol=1e-9, rtol=0.0):
        U, _, Vt = np.linalg.svd(C)
        C = U @ Vt
        r.warn("imu.mounting", f"rows are orthonormal to {off:.1g} only: the nearest rotation "
               "is used")
    a, b, c = (_vec3(row) for row in C.tolist())
    return (a, b, c)


# -- the file as a whole -------------------------------------------------------------------

def _is_device_path(port: str) -> bool:
    """A port that names a device (``simulated`` in a simulated log's config does not)."""
    return "/" in port or "\\" in port or re.fullmatch(r"(?i)com\d+", port) is not None


def _check_sources(r: _Report, sources: Sequence[tuple[int, SourceConfig]],
                   complete: bool) -> None:
    if not sources and complete:
        r.warn("sources", "none: enough to replay or import a log, not to `uwbd run`")
        return
    names: dict[str, int] = {}
    ports: dict[str, int] = {}
    for i, s in sources:
        if s.name in names:
            r.error(f"sources[{i}].name", f"{_show(s.name)} is sources[{names[s.name]}]'s name "
                    "too: names must be unique")
        names.setdefault(s.name, i)
        if _is_device_path(s.port) and s.port in ports:
            r.error(f"sources[{i}].port", f"{_show(s.port)} is sources[{ports[s.port]}]'s port "
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


def _check_anchors(r: _Report, anchors: Mapping[int, Vec3], keys: Mapping[int, str],
                   complete: bool, sources: Sequence[tuple[int, SourceConfig]],
                   fusion: Mapping[str, Any]) -> None:
    def name(anchor_id: int) -> str:
        return f"anchors.{_key(keys[anchor_id])}"

    far = [a for a, p in anchors.items() if max(abs(x) for x in p) > MAX_ANCHOR_COORD_M]
    for a in far:
        r.error(name(a), f"{_show(list(anchors[a]))}: more than {MAX_ANCHOR_COORD_M / 1000:g} "
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
    uwb = [(i, s.driver) for i, s in sources if s.driver in _DRIVERS and _DRIVERS[s.driver].uwb]
    if not uwb:
        return  # for replay or import, or without UWB (an error of its own)
    for a in ids:
        if not any(a in _DRIVERS[d].anchor_ids for _, d in uwb):
            said = "; ".join(f"{d} (sources[{i}]): {_DRIVERS[d].ids_said}" for i, d in uwb)
            r.error(name(a), f"id {a} is not one the UWB source can report ({said})")
    ranges_only = [(i, d) for i, d in uwb if not _DRIVERS[d].anchor_positions]
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


def _check_fusion(r: _Report, fusion: Mapping[str, Any], anchors: Mapping[int, Vec3]) -> None:
    if "height_range_m" in fusion:
        lo, hi = fusion["height_range_m"]
        if not lo < hi:
            r.error("fusion.height_range_m", f"expected [lowest, highest] in m, lowest < "
                    f"highest, got {_show(fusion['height_range_m'])}")
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


def _check_imu(r: _Report, imu: Mapping[str, Any], lever: Vec3) -> None:
    for key, default in _NOISE_DEFAULTS.items():
        if key in imu and not (default / NOISE_PLAUSIBLE_FACTOR <= imu[key]
                               <= default * NOISE_PLAUSIBLE_FACTOR):
            r.warn(f"imu.{key}", f"{imu[key]:g} is more than {NOISE_PLAUSIBLE_FACTOR:g}x off "
                   f"the default {default:g}: is it in the unit of the key's name?")
    for key, (lo, hi, lo_said, hi_said, unit) in _FULL_SCALE_PLAUSIBLE.items():
        if key in imu and not lo <= imu[key] <= hi:
            r.warn(f"imu.{key}", f"{imu[key]:g} {unit} is outside {lo_said}..{hi_said}: is it "
                   f"in {unit}?")
    if math.hypot(*lever) > 10.0:
        r.warn("imu.lever_arm_m", f"{math.hypot(*lever):.1f} m from the IMU to the antenna")


def _check_zenoh(r: _Report, zenoh: Mapping[str, Any]) -> None:
    good: dict[str, list[tuple[int, str]]] = {}
    for key in ("connect", "listen"):
        good[key] = []
        seen: set[str] = set()
        for k, endpoint in enumerate(zenoh.get(key, [])):
            problem = endpoint_problem(endpoint)
            if problem is not None:
                r.error(f"zenoh.{key}[{k}]", f"{_show(endpoint)}: {problem}")
                continue
            if endpoint in seen:
                r.warn(f"zenoh.{key}[{k}]", f"{_show(endpoint)} is listed twice")
            seen.add(endpoint)
            good[key].append((k, endpoint))
    if zenoh.get("mode") == "client" and not zenoh.get("connect"):
        r.error("zenoh.mode", "\"client\" needs a zenoh.connect endpoint (a router or peer)")
    prefix = zenoh.get("prefix", "").strip("/")
    if prefix and any(c in prefix for c in "*$?#"):
        r.error("zenoh.prefix", f"{_show(zenoh['prefix'])}: no wildcards (*, $*) nor # or ? in "
                "a key to publish on")
        prefix = ""
    if good["connect"] or good["listen"] or prefix:
        _check_with_zenoh(r, zenoh, good, prefix)


def _check_with_zenoh(r: _Report, zenoh_table: Mapping[str, Any],
                      endpoints: Mapping[str, list[tuple[int, str]]], prefix: str) -> None:
    """Zenoh's own parser as a second opinion on the endpoints and the key prefix."""
    import zenoh  # noqa: PLC0415 - only for configs that name endpoints

    def said(err: zenoh.ZError) -> str:  # without the Rust source location
        return re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(err))

    for key, listed in endpoints.items():
        for k, endpoint in listed:
            try:
                zenoh.Config.from_json5(json.dumps({key: {"endpoints": [endpoint]}}))
            except zenoh.ZError as err:
                r.error(f"zenoh.{key}[{k}]", f"{_show(endpoint)}: Zenoh: {said(err)}")
    if prefix:
        try:
            zenoh.KeyExpr(f"{prefix}/pose")
        except zenoh.ZError as err:
            r.error("zenoh.prefix", f"{_show(zenoh_table['prefix'])}: Zenoh: {said(err)}")


def endpoint_problem(endpoint: str) -> str | None:
    """What is wrong with a Zenoh endpoint ``<protocol>/<address>[?<metadata>][#<config>]``,
    or ``None``."""
    locator = endpoint.partition("#")[0].partition("?")[0]
    protocol, slash, address = locator.partition("/")
    if not slash or not protocol:
        return "expected <protocol>/<address>, e.g. tcp/192.168.1.10:7447"
    if protocol not in ZENOH_PROTOCOLS:
        return f"unknown protocol {_show(protocol)}" + _known(protocol, ZENOH_PROTOCOLS)
    if not address:
        return f"no address after {protocol}/"
    if protocol in _HOST_PORT_PROTOCOLS:
        return _host_port_problem(address)
    if protocol == "unixsock-stream" and not address.startswith("/"):
        return "expected an absolute socket path (unixsock-stream//run/uwbd/zenoh.sock)"
    return None


def _host_port_problem(address: str) -> str | None:
    if address.startswith("["):
        host, bracket, rest = address[1:].partition("]")
        if not bracket or not rest.startswith(":"):
            return "expected [IPv6 address]:port, e.g. [::1]:7447"
        port = rest[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return f"{_show(host)} is not an IPv6 address"
    else:
        if address.count(":") > 1:
            return "an IPv6 address goes in brackets: [::1]:7447"
        host, colon, port = address.rpartition(":")
        if not colon or not host:
            return "expected host:port, e.g. 192.168.1.10:7447"
        if re.fullmatch(r"[\d.]+", host):
            try:
                ipaddress.IPv4Address(host)
            except ValueError:
                return f"{_show(host)} is not an IPv4 address"
        elif not _HOSTNAME.fullmatch(host):
            return f"{_show(host)} is not a host name"
    if not port.isascii() or not port.isdigit() or int(port) > 65535:
        return f"port {_show(port)}: expected 0..65535"
    return None


_FILTER_NAMES = {  # FilterConfig field (or word) in a filter error -> the config's key
    "mounting_rotation": "imu.mounting", "lever_arm_m": "imu.lever_arm_m",
    "min_anchors": "fusion.min_anchors", "max_range_m": "fusion.max_range_m",
    "min_range_m": "fusion.max_range_m", "gate probability": "fusion.gate_probability",
    "tag side": "fusion.tag_side", "height_range_m": "fusion.height_range_m",
}
_FILTER_WORDS = re.compile("|".join(re.escape(w) for w in _FILTER_NAMES))


def _check_filter(r: _Report, config: Config) -> None:
    try:
        Filter(config.filter_config())
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        found = _FILTER_WORDS.search(text)
        r.error(_FILTER_NAMES[found.group()] if found else "fusion",
                "the filter cannot use it: "
                + _FILTER_WORDS.sub(lambda m: _FILTER_NAMES[m.group()], text))


# -- overrides -----------------------------------------------------------------------------

def apply_overrides(text: str, overrides: Sequence[str], where: str = "<config>") -> str:
    """``text`` with each ``section.key=value`` of ``overrides`` set, as a TOML document.

    The value is TOML (``0.2``, ``false``, ``"loose"``, ``[1, 2, 0.5]``), or a bare word taken
    as a string (``loose``, ``/dev/ttyUSB1``). ``sources.<name>.<key>`` (or
    ``sources[<index>].<key>``) sets a key of a ``[[sources]]`` entry. A problem with an
    override is a :class:`ConfigError` naming it (``--set fusion.zupt=maybe: expected true
    or false, got "maybe" (a string)``); the rest of the file is checked by :func:`parse`.
    Without overrides, ``text`` comes back as it is (comments and all).
    """
    if not overrides:
        return text
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{where}: {err}") from err
    for item in overrides:
        _apply_override(doc, item, where)
    said = " ".join(f"--set {item}" for item in overrides)
    return f"# {_one_line(where)} with {_one_line(said)}\n" + dump_toml(doc)


def _apply_override(doc: dict[str, Any], item: str, where: str) -> None:
    def fail(what: str) -> ConfigError:
        return ConfigError(f"--set {_one_line(item)}: {what}")

    path, equals, raw = item.partition("=")
    path, raw = path.strip(), raw.strip()
    if not equals or not path:
        raise fail("expected section.key=value (fusion.zupt=false)")
    value = _override_value(raw, fail)
    source = re.fullmatch(r"sources(?:\[(\d+)\]|\.(.+))\.([^.]+)", path)
    if source is not None:
        index, name, key = source.groups()
        table = _override_source(doc, int(index) if index is not None else None, name, fail,
                                 where)
        spec = _SOURCE_SPEC.get(key)
        if spec is None:
            raise fail(f"unknown key {key!r}" + _known(key, list(_SOURCE_SPEC)))
        problem = spec.problem(value)
        if problem is None and key == "driver" and value not in PARSERS:
            problem = f"unknown driver {_show(value)} (known: {', '.join(PARSERS)})"
        if problem is not None:
            raise fail(problem)
        table[key] = value
        return
    section, dot, key = path.partition(".")
    key = key.strip('"')
    if section == "sources":
        raise fail("expected sources.<name>.<key> or sources[<index>].<key>")
    if section not in _SECTIONS:
        raise fail(f"unknown section {section!r}" + _known(section, _SECTIONS))
    if not dot or not key:
        raise fail(f"expected {section}.<key>=value")
    table = doc.setdefault(section, {})
    if not isinstance(table, dict):
        raise fail(f"{section} in {where} is not a table")
    if section == "anchors":
        anchor_id = _anchor_id(key)
        if anchor_id is None:
            raise fail("an anchor id is an integer of 0 or more (\"3\", \"0x1151\")")
        if not _VEC3.ok(value):
            raise fail(f"expected {_VEC3.what}, got {_show(value)} ({_type_name(value)})")
        for other in [k for k in table if _anchor_id(k) == anchor_id]:
            del table[other]  # the same anchor, spelt otherwise ("0x3" for "3")
    else:
        spec = _TABLES[section].get(key)
        if spec is None:
            raise fail(f"unknown key {section}.{key}" + _known(key, sorted(_TABLES[section])))
        problem = spec.problem(value)
        if problem is None and key == "mounting":
            problem = _rotation_problem(value)
        if problem is not None:
            raise fail(problem)
    table[key] = value


def _override_source(doc: dict[str, Any], index: int | None, name: str | None,
                     fail: Callable[[str], ConfigError], where: str) -> dict[str, Any]:
    entries = doc.get("sources", [])
    if not isinstance(entries, list):
        raise fail(f"sources in {where} is not an array of tables")
    tables = [s for s in entries if isinstance(s, dict)]
    if index is not None:
        if not 0 <= index < len(entries) or not isinstance(entries[index], dict):
            raise fail(f"no sources[{index}] ({len(entries)} sources)")
        found: dict[str, Any] = entries[index]
        return found
    named = [s for s in tables if s.get("name") == name]
    if not named:
        names = [str(s.get("name")) for s in tables]
        raise fail(f"no source named {name!r}" + _known(name or "", names, "sources"))
    return named[0]


def _override_value(raw: str, fail: Callable[[str], ConfigError]) -> Any:
    if not raw:
        raise fail("no value after =")
    try:
        return tomllib.loads(f"value = {raw}")["value"]
    except tomllib.TOMLDecodeError as err:
        if re.fullmatch(r"[^\s\"'\[\]{}=#,]+", raw):
            return raw  # a bare word: a string
        said = re.sub(r"\s*\(at (line \d+, column \d+|end of document)\)", "", str(err))
        raise fail(f"not a TOML value ({said}); quote a string: \"...\"") from err


def _rotation_problem(rows: list[list[float]]) -> str | None:
    r = _Report("")
    _mounting(r, rows)
    return r.errors[0].split(": ", 2)[2] if r.errors else None


# -- writing -------------------------------------------------------------------------------

def dump_toml(doc: Mapping[str, Any]) -> str:
    """A TOML document for ``doc`` (as ``tomllib`` reads one): plain keys first, then each
    table and array of tables; values inline."""
    lines = [f"{_key(k)} = {_value(v)}" for k, v in doc.items()
             if not isinstance(v, dict) and not _is_tables(v)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += ["", f"[{_key(k)}]", *(f"{_key(kk)} = {_value(vv)}" for kk, vv in v.items())]
        elif _is_tables(v):
            for t in v:
                lines += ["", f"[[{_key(k)}]]",
                          *(f"{_key(kk)} = {_value(vv)}" for kk, vv in t.items())]
    return "\n".join(lines).lstrip("\n") + "\n"


def _is_tables(v: object) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(t, dict) for t in v)


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}


def _string(s: str) -> str:
    return '"' + "".join(_ESCAPES.get(c, f"\\u{ord(c):04x}" if ord(c) < 0x20 or c == "\x7f"
                                      else c) for c in s) + '"'


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _string(k)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else
                                                 "inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return ("{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
                if v else "{}")
    if isinstance(v, (datetime.date, datetime.time)):  # datetime is a date
        return v.isoformat()
    raise TypeError(f"not a TOML value: {v!r}")


def _show(v: Any) -> str:
    """A value as the TOML would spell it, cut short."""
    try:
        text = _value(v)
    except TypeError:
        text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_name(v: Any) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a float"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return f"an array of {len(v)}"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, datetime.datetime):
        return "a date-time"
    if isinstance(v, datetime.date):
        return "a date"
    if isinstance(v, datetime.time):
        return "a time"
    return type(v).__name__


def _maybe(word: str, known: Sequence[str]) -> str:
    """`` (did you mean X?)`` for the closest of ``known``, or nothing."""
    close = difflib.get_close_matches(word, list(known), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _known(word: str, known: Sequence[str], label: str = "known") -> str:
    """`` (did you mean X? known: A, B, X)``, the question only when one is close."""
    close = difflib.get_close_matches(word, list(known), n=1)
    listed = f"{label}: {', '.join(known) or 'none'}"
    return f" (did you mean {close[0]}? {listed})" if close else f" ({listed})"


def _one_line(s: str) -> str:
    return "".join(c if c >= " " and c != "\x7f" else f"\\u{ord(c):04x}" for c in s)


def to_toml(sources: Sequence[SourceConfig], anchors_m: Mapping[int, Sequence[float]],
            mounting: Sequence[Sequence[float]], lever_arm_m: Sequence[float],
            fusion: Mapping[str, Any] | None = None,
            imu: Mapping[str, float] | None = None) -> str:
    """A config file for these settings (what ``uwbd simulate`` and ``import`` store)."""
    def num(v: float) -> str:
        return repr(float(v))

    def vec(v: Sequence[float]) -> str:
        return "[" + ", ".join(num(x) for x in v) + "]"

    lines = []
    for s in sources:
        lines += ["[[sources]]", f"name = {_string(s.name)}", f"driver = {_string(s.driver)}",
                  f"port = {_string(s.port)}", f"baud = {s.baud}", ""]
    lines.append("[anchors]")
    lines += [f'"{k}" = {vec(v)}' for k, v in sorted(anchors_m.items())]
    lines += ["", "[imu]", "mounting = [" + ", ".join(vec(r) for r in mounting) + "]",
              f"lever_arm_m = {vec(lever_arm_m)}"]
    lines += [f"{key} = {num(value)}" for key, value in (imu or {}).items()]
    lines += ["", "[fusion]"]
    for key, value in (fusion or {}).items():
        integer = key in _FUSION_SPEC and _FUSION_SPEC[key].kind is _INTEGER
        lines.append(f"{key} = " + (_value(value) if isinstance(value, (str, bool, list))
                                    or integer else num(value)))
    return "\n".join(lines) + "\n"
