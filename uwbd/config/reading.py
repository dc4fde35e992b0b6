"""Reading a config: :func:`load` (a file, with ``--set`` overrides) and :func:`parse` (the
TOML text): each section's keys checked against the schema, every problem at once, then the
checks of the file as a whole."""

from __future__ import annotations

import math
import stat
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivers import PARSERS
from uwbd.config.checks import (
    Report,
    check_anchors,
    check_filter,
    check_fusion,
    check_imu,
    check_range_model,
    check_ros2,
    check_sources,
    mounting_rotation,
)
from uwbd.config.model import (
    IMU_INTRINSIC_KEYS,
    IMU_INTRINSIC_VECTORS,
    IMU_LIMIT_KEYS,
    IMU_NOISE_KEYS,
    Config,
    ConfigError,
    SourceConfig,
    Vec3,
    vec3,
)
from uwbd.config.overrides import apply_overrides, toml_document
from uwbd.config.schema import (
    SECTIONS,
    SOURCE_SPEC,
    TABLES,
    VEC3,
    XYZW,
    Key,
    anchor_id,
)
from uwbd.config.spelling import known, show, toml_key, type_name
from uwbd.config.zenoh_checks import check_zenoh
from uwbd.fusion.core.rotation import quat_to_matrix

Rotation = tuple[Vec3, Vec3, Vec3]
QUATERNION_TOLERANCE = 1e-3  # a quaternion typed to 4 digits is this close to unit norm

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover - Python 3.10
    pass

MAX_CONFIG_BYTES = 1 << 20  # a config file is a few kB: more is some other file


def load(path: Path, overrides: Sequence[str] = ()) -> Config:
    """The config file at ``path`` with ``overrides`` (``section.key=value``) applied."""
    where = str(path)
    try:
        mode = path.stat().st_mode
        if stat.S_ISDIR(mode):
            raise ConfigError(f"{where}: Is a directory, not a config file")
        if not stat.S_ISREG(mode):
            raise ConfigError(f"{where}: not a regular file (a FIFO or a device): give a "
                              "config file")
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


def parse(text: str, where: str = "<config>") -> Config:
    """The config in ``text`` (``where``: the file, for messages), every problem at once."""
    doc = toml_document(text, where)
    r = Report(where)
    _unknown_keys(r, doc, SECTIONS, "")
    sources, sources_complete = _sources(r, doc)
    anchors, anchor_keys, anchors_complete, anchor_axes = _anchors(r, doc)
    tables = {name: _table(r, doc, name, spec) for name, spec in TABLES.items()}
    imu, fusion, zenoh = tables["imu"], tables["fusion"], tables["zenoh"]
    if "config" in zenoh and Path(where).is_file():  # a Zenoh config file beside this one
        zenoh["config"] = str(Path(where).parent / Path(zenoh["config"]).expanduser())
    mounting = mounting_rotation(r, imu.get("mounting"))
    lever = vec3(imu.get("lever_arm_m", [0.0, 0.0, 0.0]))
    check_sources(r, sources, sources_complete)
    check_anchors(r, anchors, anchor_keys, anchors_complete, sources, fusion)
    check_fusion(r, fusion, anchors)
    check_range_model(r, tables["range_model"], fusion, anchors, anchor_axes)
    check_imu(r, imu, lever)
    check_zenoh(r, zenoh)
    check_ros2(r, tables["ros2"], zenoh)
    if r.errors:
        raise ConfigError(r.errors, r.warnings)
    config = Config(
        sources=tuple(s for _, s in sources), anchors_m=anchors, anchor_axes=anchor_axes,
        mounting=mounting,
        lever_arm_m=lever,
        imu_noise={k: float(imu[k]) for k in IMU_NOISE_KEYS if k in imu},
        imu_limits={k: float(imu[k]) for k in IMU_LIMIT_KEYS if k in imu},
        imu_intrinsics={k: vec3(imu[k]) if k in IMU_INTRINSIC_VECTORS else float(imu[k])
                        for k in IMU_INTRINSIC_KEYS if k in imu},
        fusion=fusion, range_model=tables["range_model"], pipeline=tables["pipeline"],
        log=tables["log"], zenoh=zenoh, robot=tables["robot"], ros2=tables["ros2"], text=text,
        warnings=tuple(r.warnings))
    check_filter(r, config)  # a last net: what only the filter understands
    if r.errors:
        raise ConfigError(r.errors, r.warnings)
    return config


def _unknown_keys(r: Report, table: Mapping[str, Any], names: Sequence[str], prefix: str) -> None:
    for key in table:
        if key not in names:
            r.error(prefix + toml_key(key), "unknown key" + known(key, sorted(names)))


def _table(r: Report, doc: Mapping[str, Any], name: str, spec: Mapping[str, Key]
           ) -> dict[str, Any]:
    """The section ``name``, its keys checked against ``spec``: only the valid ones kept."""
    table = doc.get(name, {})
    if not isinstance(table, dict):
        r.error(name, f"expected a table ([{name}]), got {show(table)} ({type_name(table)})")
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
            r.error(f"{name}.{toml_key(key)}", problem)
    return good


def _sources(r: Report, doc: Mapping[str, Any]) -> tuple[list[tuple[int, SourceConfig]], bool]:
    """The valid ``[[sources]]`` with their index, and whether all were."""
    entries = doc.get("sources", [])
    if not isinstance(entries, list):
        r.error("sources", f"expected an array of tables ([[sources]]), got {show(entries)} "
                           f"({type_name(entries)})")
        return [], False
    out = []
    complete = True
    for i, s in enumerate(entries):
        key = f"sources[{i}]"
        if not isinstance(s, dict):
            r.error(key, f"expected a table ([[sources]]), got {show(s)} ({type_name(s)})")
            complete = False
            continue
        _unknown_keys(r, s, tuple(SOURCE_SPEC), f"{key}.")
        ok = True
        for name, spec in SOURCE_SPEC.items():
            if name not in s:
                if name != "baud":
                    r.error(f"{key}.{name}", f"required: {spec.kind.what}")
                    ok = False
                continue
            problem = spec.problem(s[name])
            if problem is None and name == "driver" and s[name] not in PARSERS:
                problem = f"unknown driver {show(s[name])}" + known(s[name], list(PARSERS))
            if problem is not None:
                r.error(f"{key}.{name}", problem)
                ok = False
        if ok:
            out.append((i, SourceConfig(s["name"], s["driver"], s["port"],
                                        s.get("baud", 115200))))
        complete = complete and ok
    return out, complete


def _anchors(r: Report, doc: Mapping[str, Any]
             ) -> tuple[dict[int, Vec3], dict[int, str], bool, dict[int, Rotation]]:
    """The valid anchors, their keys as spelt in the file, whether all were valid, and the
    orientations of those given in the table form (``{ position_m = [x, y, z],
    orientation_xyzw = [qx, qy, qz, qw] }``: the anchor's axes in the navigation frame)."""
    table = doc.get("anchors", {})
    if not isinstance(table, dict):
        r.error("anchors", f"expected a table ([anchors]), got {show(table)} "
                           f"({type_name(table)})")
        return {}, {}, False, {}
    anchors: dict[int, Vec3] = {}
    keys: dict[int, str] = {}
    axes: dict[int, Rotation] = {}
    complete = True
    for key, value in table.items():
        name = f"anchors.{toml_key(key)}"
        found = anchor_id(key)
        if found is None:
            r.error(name, "not an integer id (\"3\", \"0x1151\") of 0 or more")
            complete = False
            continue
        position, rotation = _anchor_entry(r, name, value)
        if position is None:
            complete = False
            continue
        if found in keys:
            r.error(name, f"the same id as anchors.{toml_key(keys[found])}")
            complete = False
            continue
        anchors[found], keys[found] = position, key
        if rotation is not None:
            axes[found] = rotation
    return anchors, keys, complete, axes


def _anchor_entry(r: Report, name: str, value: Any) -> tuple[Vec3 | None, Rotation | None]:
    """One ``[anchors]`` entry: ``[x, y, z]``, or ``{ position_m = [x, y, z],
    orientation_xyzw = [qx, qy, qz, qw] }`` (a unit quaternion, the anchor's axes to the
    navigation frame, for the range model's anchor term)."""
    if VEC3.ok(value):
        return vec3(value), None
    if not isinstance(value, dict):
        also = "" if isinstance(value, list) else \
            ", or { position_m = [x, y, z], orientation_xyzw = [qx, qy, qz, qw] }"
        r.error(name, f"expected {VEC3.what}{also}, got {show(value)} ({type_name(value)})")
        return None, None
    unknown = sorted(set(value) - {"position_m", "orientation_xyzw"})
    if unknown:
        r.error(f"{name}.{toml_key(unknown[0])}", "unknown key (an anchor takes position_m "
                "and orientation_xyzw)")
        return None, None
    position: Any = value.get("position_m")
    if not VEC3.ok(position):
        r.error(f"{name}.position_m", f"expected {VEC3.what}, got {show(position)}")
        return None, None
    q = value.get("orientation_xyzw")
    if q is None:
        return vec3(position), None
    if not XYZW.ok(q):
        r.error(f"{name}.orientation_xyzw", f"expected {XYZW.what}, got {show(q)}")
        return None, None
    norm = math.sqrt(sum(float(x) ** 2 for x in q))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        r.error(f"{name}.orientation_xyzw", f"a quaternion of norm {norm:.6g}: expected a "
                "unit quaternion (x, y, z, w)")
        return None, None
    qx, qy, qz, qw = (float(x) / norm for x in q)
    rows = quat_to_matrix(np.array([qw, qx, qy, qz])).tolist()
    return vec3(position), (vec3(rows[0]), vec3(rows[1]), vec3(rows[2]))
