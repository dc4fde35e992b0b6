"""uwbd's TOML configuration, validated into typed objects.

Every problem is a :class:`ConfigError` naming the file and the key (``cfg.toml: fusion.mode:
expected one of loose, tight, got 'tite'``); unknown keys are errors too, since a misspelt
option that is silently ignored is worse than none. Sections::

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
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers import PARSERS
from uwbd.fusion.eskf import ImuNoise
from uwbd.fusion.filter import Filter
from uwbd.fusion.gating import GatingPolicy
from uwbd.fusion.imu_check import ImuLimits
from uwbd.fusion.robust import RobustPolicy
from uwbd.fusion.settings import IDENTITY3, FilterConfig, Mode

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Vec3 = tuple[float, float, float]


class ConfigError(ValueError):
    """A configuration problem, with the file and key it is about."""


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


Number = (int, float)
_PIPELINE_KEYS: dict[str, type | tuple[type, ...]] = {
    "aligner_wait_ms": Number, "pose_rate_hz": Number, "status_period_s": Number}
_LOG_KEYS: dict[str, type | tuple[type, ...]] = {
    "directory": str, "rotate_mb": Number, "rotate_minutes": Number}
_ZENOH_KEYS: dict[str, type | tuple[type, ...]] = {
    "enabled": bool, "mode": str, "connect": list, "listen": list, "prefix": str,
    "multicast_scouting": bool}
# [imu] key -> ImuNoise field
IMU_NOISE_KEYS = {"acc_noise_mps2_rthz": "acc", "gyro_noise_rps_rthz": "gyro",
                  "acc_bias_walk_mps3_rthz": "acc_bias", "gyro_bias_walk_rps2_rthz": "gyro_bias"}
IMU_LIMIT_KEYS = ("acc_full_scale_mps2", "gyro_full_scale_rps")  # ImuLimits fields
MULTIPATH_SIGMA_M = 0.07  # the default time-correlated range error (real installations)
_FUSION_KEYS: dict[str, type | tuple[type, ...]] = {
    "mode": str, "range_sigma_m": (int, float), "range_bias_states": bool,
    "range_bias_sigma_m": (int, float), "tag_delay_sigma_m": (int, float), "zupt": bool,
    "nhc": bool, "known_height_m": (int, float), "gate_probability": (int, float),
    "min_anchors": int, "max_range_m": (int, float), "robust": bool,
    "multipath_sigma_m": (int, float), "multipath_tau_s": (int, float), "tag_side": str,
    "height_range_m": list,
}


def load(path: Path) -> Config:
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"{path}: {err.strerror}") from err
    return parse(text, str(path))


def parse(text: str, where: str = "<config>") -> Config:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{where}: {err}") from err
    _only(doc, {"sources", "anchors", "imu", "fusion", "pipeline", "log", "zenoh"}, where, "")
    sources = tuple(_source(s, where, i) for i, s in enumerate(_list(doc, "sources", where)))
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: sources: names must be unique, got {names}")
    anchors = {}
    for key, value in _table(doc, "anchors", where).items():
        try:
            anchor_id = int(key, 0)
        except ValueError as err:
            raise ConfigError(f"{where}: anchors.{key}: not an integer id") from err
        anchors[anchor_id] = _vec(value, where, f"anchors.{key}")
    imu = _table(doc, "imu", where)
    _only(imu, {"mounting", "lever_arm_m", *IMU_NOISE_KEYS, *IMU_LIMIT_KEYS}, where, "imu.")
    numbers = {}
    for key in (*IMU_NOISE_KEYS, *IMU_LIMIT_KEYS):
        if key in imu:
            value = imu[key]
            if (isinstance(value, bool) or not isinstance(value, (int, float))
                    or not math.isfinite(value) or value <= 0):
                raise ConfigError(f"{where}: imu.{key}: expected a positive number, "
                                  f"got {value!r}")
            numbers[key] = float(value)
    imu_noise = {k: v for k, v in numbers.items() if k in IMU_NOISE_KEYS}
    imu_limits = {k: v for k, v in numbers.items() if k in IMU_LIMIT_KEYS}
    mounting = IDENTITY3
    if "mounting" in imu:
        rows = imu["mounting"]
        if not isinstance(rows, list) or len(rows) != 3:
            raise ConfigError(f"{where}: imu.mounting: expected 3 rows of 3 numbers")
        mounting = (_vec(rows[0], where, "imu.mounting[0]"),
                    _vec(rows[1], where, "imu.mounting[1]"),
                    _vec(rows[2], where, "imu.mounting[2]"))
    lever = _vec(imu.get("lever_arm_m", [0, 0, 0]), where, "imu.lever_arm_m")
    fusion = _typed_table(doc, "fusion", _FUSION_KEYS, where)
    pipeline = _typed_table(doc, "pipeline", _PIPELINE_KEYS, where)
    log = _typed_table(doc, "log", _LOG_KEYS, where)
    zenoh = _typed_table(doc, "zenoh", _ZENOH_KEYS, where)
    if zenoh.get("mode", "peer") not in ("peer", "client", "router"):
        raise ConfigError(f"{where}: zenoh.mode: expected peer, client or router, "
                          f"got {zenoh['mode']!r}")
    for key in ("connect", "listen"):
        if not all(isinstance(e, str) for e in zenoh.get(key, [])):
            raise ConfigError(f"{where}: zenoh.{key}: expected a list of endpoint strings")
    for section, table in (("pipeline", pipeline), ("log", log)):
        for key, value in table.items():
            zero_ok = key == "aligner_wait_ms"
            if not isinstance(value, str) and not (value > 0 or (zero_ok and value == 0)):
                raise ConfigError(f"{where}: {section}.{key}: must be positive, got {value}")
    for key, zero_ok in (("range_sigma_m", False), ("range_bias_sigma_m", True),
                         ("tag_delay_sigma_m", True), ("multipath_sigma_m", True),
                         ("multipath_tau_s", False)):
        value = fusion.get(key, 1.0)
        if not (math.isfinite(value) and (value > 0 or (zero_ok and value == 0))):
            raise ConfigError(f"{where}: fusion.{key}: must be "
                              f"{'zero or more' if zero_ok else 'positive'}, got {value}")
    if fusion.get("tag_side", "auto") not in ("auto", "below", "above"):
        raise ConfigError(f"{where}: fusion.tag_side: expected auto, below or above, "
                          f"got {fusion['tag_side']!r}")
    if "height_range_m" in fusion:
        hr = fusion["height_range_m"]
        if (len(hr) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                    and math.isfinite(v) for v in hr) or not hr[0] < hr[1]):
            raise ConfigError(f"{where}: fusion.height_range_m: expected [lowest, highest] "
                              f"in m, lowest < highest, got {hr!r}")
    if "mode" in fusion and fusion["mode"] not in {m.value for m in Mode}:
        raise ConfigError(f"{where}: fusion.mode: expected one of "
                          f"{', '.join(m.value for m in Mode)}, got {fusion['mode']!r}")
    config = Config(sources, anchors, mounting, lever, imu_noise, imu_limits, fusion, pipeline,
                    log, zenoh, text)
    try:
        Filter(config.filter_config())  # the filter checks what only it understands
    except ValueError as err:
        raise ConfigError(f"{where}: {err}") from err
    return config


def _typed_table(doc: dict[str, Any], name: str, spec: dict[str, type | tuple[type, ...]],
                 where: str) -> dict[str, Any]:
    table = _table(doc, name, where)
    _only(table, set(spec), where, f"{name}.")
    for key, value in table.items():
        kind = spec[key]
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            raise ConfigError(f"{where}: {name}.{key}: wrong type {type(value).__name__}")
    return table


def _only(table: dict[str, Any], allowed: set[str], where: str, prefix: str) -> None:
    for key in table:
        if key not in allowed:
            raise ConfigError(f"{where}: {prefix}{key}: unknown key "
                              f"(known: {', '.join(sorted(allowed))})")


def _table(doc: dict[str, Any], key: str, where: str) -> dict[str, Any]:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: {key}: expected a table")
    return value


def _list(doc: dict[str, Any], key: str, where: str) -> list[Any]:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise ConfigError(f"{where}: {key}: expected an array of tables ([[{key}]])")
    return value


def _vec(value: Any, where: str, key: str) -> Vec3:
    if (not isinstance(value, list) or len(value) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) for v in value)):
        raise ConfigError(f"{where}: {key}: expected [x, y, z] of finite numbers, got {value!r}")
    return (float(value[0]), float(value[1]), float(value[2]))


def _source(s: Any, where: str, index: int) -> SourceConfig:
    key = f"sources[{index}]"
    if not isinstance(s, dict):
        raise ConfigError(f"{where}: {key}: expected a table")
    _only(s, {"name", "driver", "port", "baud"}, where, f"{key}.")
    for required in ("name", "driver", "port"):
        if not isinstance(s.get(required), str):
            raise ConfigError(f"{where}: {key}.{required}: required, a string")
    if s["driver"] not in PARSERS:
        raise ConfigError(f"{where}: {key}.driver: unknown driver {s['driver']!r} "
                          f"(known: {', '.join(PARSERS)})")
    baud = s.get("baud", 115200)
    if not isinstance(baud, int) or isinstance(baud, bool) or baud <= 0:
        raise ConfigError(f"{where}: {key}.baud: expected a positive integer")
    return SourceConfig(s["name"], s["driver"], s["port"], baud)


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
        lines += ["[[sources]]", f'name = "{s.name}"', f'driver = "{s.driver}"',
                  f'port = "{s.port}"', f"baud = {s.baud}", ""]
    lines.append("[anchors]")
    lines += [f'"{k}" = {vec(v)}' for k, v in sorted(anchors_m.items())]
    lines += ["", "[imu]", "mounting = [" + ", ".join(vec(r) for r in mounting) + "]",
              f"lever_arm_m = {vec(lever_arm_m)}"]
    lines += [f"{key} = {num(value)}" for key, value in (imu or {}).items()]
    lines += ["", "[fusion]"]
    for key, value in (fusion or {}).items():
        lines.append(f"{key} = " + (f'"{value}"' if isinstance(value, str)
                                    else str(value).lower() if isinstance(value, bool)
                                    else num(value)))
    return "\n".join(lines) + "\n"
