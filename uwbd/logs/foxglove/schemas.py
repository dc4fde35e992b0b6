"""The JSON Schemas of every channel (:mod:`uwbd.logs.foxglove` says which and why)."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from typing import Any, Union

from drivers.frames import ImuSample, UwbRanges

Schema = dict[str, Any]
Vec3 = tuple[float, float, float]


T_NS_TEXT = ("receive time, integer ns since the Unix epoch (exact for Python, Rust, C++; "
             "above 2^53, so JavaScript rounds it: use timestamp)")


def stamp(t_ns: int) -> dict[str, int]:
    """``{sec, nsec}`` of a time in ns (Foxglove's time)."""
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


# -- building blocks --------------------------------------------------------------------------

def _num(text: str) -> Schema:
    return {"type": "number", "description": text}


def _obj(title: str, text: str, props: Mapping[str, Schema],
         required: tuple[str, ...] = (), closed: bool = False) -> Schema:
    out: Schema = {"title": title, "description": text, "type": "object",
                   "properties": dict(props)}
    if required:
        out["required"] = list(required)
    if closed:
        out["additionalProperties"] = False
    return out


def time_schema(text: str) -> Schema:
    return {"title": "time", "description": text, "type": "object", "properties": {
        "sec": {"type": "integer", "minimum": 0, "description": "whole seconds since the "
                "Unix epoch"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999,
                 "description": "nanoseconds past sec"}}, "required": ["sec", "nsec"]}


def _duration(text: str) -> Schema:
    return {"title": "duration", "description": text, "type": "object", "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}


def _vector3(text: str, title: str = "foxglove.Vector3") -> Schema:
    return _obj(title, text, {k: _num(f"{k} (m)") for k in "xyz"}, tuple("xyz"))


def _quaternion(text: str) -> Schema:
    return _obj("foxglove.Quaternion", text, {k: _num(f"{k} component") for k in "xyzw"},
                tuple("xyzw"))


def _pose(text: str) -> Schema:
    return _obj("foxglove.Pose", text, {
        "position": _vector3("position (m)"),
        "orientation": _quaternion("orientation, unit quaternion")},
        ("position", "orientation"))


def _color(text: str) -> Schema:
    return _obj("foxglove.Color", text, {k: _num(f"{k}, 0 to 1") for k in "rgba"},
                tuple("rgba"))


def _t_ns() -> Schema:
    return {"type": "integer", "description": T_NS_TEXT}


def pose_in_frame_schema(extra: Mapping[str, Schema] | None = None,
                         text: str = "a pose in a frame") -> Schema:
    """``foxglove.PoseInFrame`` (and ``t_ns``), with ``extra`` properties."""
    return _obj("foxglove.PoseInFrame", text, {
        "timestamp": time_schema("time of the pose (exact)"),
        "frame_id": {"type": "string", "description": "frame the pose is in (the config's "
                     "[robot] nav_frame_id)"},
        "pose": _pose("the body frame's origin and orientation in frame_id"),
        "t_ns": _t_ns(), **(extra or {})}, ("timestamp", "frame_id", "pose"))


def _health_schema() -> Schema:
    optional = "; absent when not known"
    return _obj("uwbd.Health", "the filter's health record (docs/health.md)", {
        "phase": {"type": "string", "description": "waiting, recovering, coasting, degraded, "
                  "aligning or tracking (only tracking is healthy)"},
        "healthy": {"type": "boolean", "description": "phase is tracking"},
        "faults": {"type": "array", "items": {"type": "string"},
                   "description": "what is wrong now"},
        "notes": {"type": "array", "items": {"type": "string"},
                  "description": "what to know, not wrong (e.g. mirror_unresolved)"},
        "since_range_s": _num("s since the last accepted UWB measurement" + optional),
        "position_sigma_m": _num("horizontal σ, √(σx² + σy²), m" + optional),
        "horizontal_protection_m": _num("horizontal protection level: the bound on the "
                                        "horizontal error at the integrity risk, m" + optional),
        "vertical_protection_m": _num("vertical protection level, m" + optional),
        "horizontal_available": {"type": "boolean", "description": "the horizontal "
                                 "protection level known and within its alert limit"},
        "vertical_available": {"type": "boolean", "description": "the vertical one too"},
        "resets": {"type": "integer", "description": "filter restarts so far"},
        "last_reset_t_ns": {"type": "integer",
                            "description": "time of the last restart, ns" + optional},
        "last_reset_reason": {"type": "string", "description": "why (empty: none)"},
        "last_reset_jump_m": _num("how far the position moved at that restart, m" + optional),
    }, required=("phase", "healthy", "faults", "notes", "resets", "last_reset_reason"),
        closed=True)


def _array(items: Schema, text: str, n: int | None = None) -> Schema:
    out: Schema = {"type": "array", "items": items, "description": text}
    if n is not None:
        out["minItems"] = out["maxItems"] = n
    return out


POSE_SCHEMA = pose_in_frame_schema({
    "velocity_mps": _array({"type": "number"}, "velocity in frame_id, m/s (x, y, z)", 3),
    "covariance": _array({"type": "number"}, "6×6 row-major over x, y, z (m) and rotation "
                         "about frame_id's x, y, z (rad), as ROS PoseWithCovariance", 36),
    "status": {"type": "string", "description": "the health record in one line"},
    "heading_observable": {"type": "boolean",
                           "description": "the heading is known (false until aligned)"},
    "health": _health_schema(),
}, "the fused pose: a foxglove.PoseInFrame plus uwbd's fields")
POSE_SCHEMA["required"] = ["timestamp", "frame_id", "pose", "t_ns", "velocity_mps",
                           "covariance", "status", "heading_observable", "health"]
POSE_SCHEMA["additionalProperties"] = False
TRUTH_SCHEMA = pose_in_frame_schema(text="ground truth (simulator, dataset or demo scenario)")

FRAME_TRANSFORM_SCHEMA = _obj(
    "foxglove.FrameTransform", "the body frame in the navigation frame, at each pose", {
        "timestamp": time_schema("time of the transform"),
        "parent_frame_id": {"type": "string", "description": "navigation frame"},
        "child_frame_id": {"type": "string", "description": "body frame"},
        "translation": _vector3("body origin in the parent frame"),
        "rotation": _quaternion("body orientation in the parent frame")},
    ("timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"))

POSES_IN_FRAME_SCHEMA = _obj(
    "foxglove.PosesInFrame", "a trajectory: recent poses, oldest first", {
        "timestamp": time_schema("time of the newest pose"),
        "frame_id": {"type": "string", "description": "frame of the poses"},
        "poses": {"type": "array", "items": _pose("a pose on the trajectory"),
                  "description": "the poses"}}, ("timestamp", "frame_id", "poses"))


def _primitive(title: str, text: str, props: Mapping[str, Schema]) -> Schema:
    return {"type": "array", "description": text,
            "items": _obj(title, text, {"pose": _pose("centre and orientation"), **props},
                          ("pose", *props))}


def _unused(title: str) -> Schema:
    """A primitive list uwbd leaves empty (Foxglove's schema wants it present)."""
    return {"type": "array", "description": f"{title}: none",
            "items": {"title": title, "type": "object", "properties": {}}}


ENTITY_FIELDS = ("timestamp", "frame_id", "id", "lifetime", "frame_locked", "metadata",
                 "arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts",
                 "models")


SCENE_UPDATE_SCHEMA = _obj(
    "foxglove.SceneUpdate", "entities of a 3D scene (the fields uwbd writes)", {
        "deletions": {"type": "array", "description": "entities to delete", "items": _obj(
            "foxglove.SceneEntityDeletion", "a deletion", {
                "timestamp": time_schema("delete matching entities older than this"),
                "type": {"title": "foxglove.SceneEntityDeletionType",
                         "description": "what to delete",
                         "oneOf": [{"title": "MATCHING_ID", "const": 0},
                                   {"title": "ALL", "const": 1}]},
                "id": {"type": "string", "description": "entity id (MATCHING_ID)"}},
            ("timestamp", "type", "id"))},
        "entities": {"type": "array", "description": "entities to add or replace", "items": _obj(
            "foxglove.SceneEntity", "a visual element", {
                "timestamp": time_schema("time of the entity"),
                "frame_id": {"type": "string", "description": "frame of reference"},
                "id": {"type": "string", "description": "replaces an entity with this id"},
                "lifetime": _duration("0: until replaced"),
                "frame_locked": {"type": "boolean", "description": "follow frame_id"},
                "metadata": {"type": "array", "description": "key/value pairs", "items": _obj(
                    "foxglove.KeyValuePair", "a key and its value", {
                        "key": {"type": "string"}, "value": {"type": "string"}},
                    ("key", "value"))},
                "arrows": _unused("foxglove.ArrowPrimitive"),
                "cubes": _unused("foxglove.CubePrimitive"),
                "spheres": _primitive("foxglove.SpherePrimitive", "spheres", {
                    "size": _vector3("diameters along x, y, z (m)"),
                    "color": _color("colour")}),
                "texts": _primitive("foxglove.TextPrimitive", "text labels", {
                    "billboard": {"type": "boolean", "description": "face the camera"},
                    "font_size": _num("font size (pixels when scale_invariant)"),
                    "scale_invariant": {"type": "boolean", "description": "size in pixels"},
                    "color": _color("colour"),
                    "text": {"type": "string", "description": "the text"}}),
                "cylinders": _unused("foxglove.CylinderPrimitive"),
                "lines": _unused("foxglove.LinePrimitive"),
                "triangles": _unused("foxglove.TriangleListPrimitive"),
                "models": _unused("foxglove.ModelPrimitive"),
            }, ENTITY_FIELDS)},
    }, ("deletions", "entities"))


# -- frames, from the dataclasses -------------------------------------------------------------

UNITS = {"_mps2": "m/s²", "_rps": "rad/s", "_mps": "m/s", "_deg": "°", "_c": "°C",
         "_ns": "ns", "_ms": "ms", "_m": "m"}


def _unit(name: str) -> str:
    return next((u for suffix, u in UNITS.items() if name.endswith(suffix)), "")


def _field_schema(name: str, hint: Any) -> tuple[Schema, bool]:
    """(schema, required) of one dataclass field from its type."""
    required = True
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (Union, types.UnionType) and type(None) in args:
        required = False
        (hint,) = (a for a in args if a is not type(None))
    unit = _unit(name)
    text = name.replace("_", " ") + (f" ({unit})" if unit else "")
    if not required:
        text += "; absent when the device does not send it"
    out = _value_schema(hint)
    out["description"] = text
    return out, required


def _value_schema(hint: Any) -> Schema:
    if dataclasses.is_dataclass(hint):
        return _dataclass_schema(hint)  # type: ignore[arg-type]
    if typing.get_origin(hint) is tuple:
        items = typing.get_args(hint)
        if len(items) == 2 and items[1] is Ellipsis:
            return {"type": "array", "items": _value_schema(items[0])}
        kinds = {_value_schema(a)["type"] for a in items}
        # a fixed-size vector; an array of arrays is valid JSON Schema but not one Foxglove
        # reads: a frame type that needs one is better logged as objects
        kind = "integer" if kinds == {"integer"} else "number"
        return {"type": "array", "items": {"type": kind}, "minItems": len(items),
                "maxItems": len(items)}
    return {"type": {int: "integer", float: "number", str: "string", bool: "boolean"}[hint]}


def _dataclass_schema(cls: type[Any]) -> Schema:
    hints = typing.get_type_hints(cls)
    props: dict[str, Schema] = {}
    required: list[str] = []
    for f in dataclasses.fields(cls):
        props[f.name], needed = _field_schema(f.name, hints[f.name])
        if needed:
            required.append(f.name)
    return _obj(f"uwbd.{cls.__name__}", (cls.__doc__ or cls.__name__).strip().split("\n")[0],
                props, tuple(required), closed=True)


def frame_schema(cls: type[Any]) -> Schema:
    """A decoded frame's record (``/imu``, ``/uwb``): ``type``, ``timestamp`` and the
    dataclass's fields (:func:`uwbd.codec.frame_to_json`)."""
    out = _dataclass_schema(cls)
    out["properties"] = {"type": {"type": "string", "description": f'"{cls.__name__}"'},
                         "timestamp": time_schema("receive time (exact)"),
                         **out["properties"]}
    out["properties"]["t_ns"] = _t_ns()
    out["required"] = ["type", "timestamp", *out["required"]]
    return out


IMU_SCHEMA = frame_schema(ImuSample)
UWB_SCHEMA = frame_schema(UwbRanges)  # its ranges' items: AnchorRange, derived the same way
FRAME_CHANNELS: dict[type[Any], tuple[str, Schema]] = {
    ImuSample: ("/imu", IMU_SCHEMA), UwbRanges: ("/uwb", UWB_SCHEMA)}


def frame_channel(cls: type[Any]) -> tuple[str, Schema]:
    """The topic and schema of a frame type's records: ``/imu``, ``/uwb``; another frame
    type (a driver's new kind) gets ``/<snake_case name>`` and a schema derived the same way."""
    known = FRAME_CHANNELS.get(cls)
    if known is None:
        topic = "/" + "".join(f"_{c.lower()}" if c.isupper() else c for c in cls.__name__)[1:]
        known = FRAME_CHANNELS[cls] = (topic, frame_schema(cls))
    return known


def _open_map(values: Schema, text: str) -> Schema:
    """An object keyed by names uwbd cannot list (anchors, sources, counters)."""
    return {"type": "object", "description": text, "properties": {},
            "additionalProperties": values}


_COUNT = {"type": "integer", "minimum": 0}
STATUS_SCHEMA = _obj("uwbd.Status", "once a second: the filter's health, counters, "
                     "parsers, ports and the log (docs/robot.md)", {
    "timestamp": time_schema("time of the status (exact)"),
    "t_ns": _t_ns(),
    "version": {"type": "string", "description": "uwbd version"},
    "filter": {"type": "string", "description": "the health record in one line"},
    "health": _health_schema(),
    "mirror": _obj("uwbd.Mirror", "the side of a plane of anchors", {
        "ambiguous": {"type": "boolean", "description": "the anchors are coplanar"},
        "side": {"type": "string", "description": "above or below them"},
        "decided_by": {"type": "string", "description": "how the side was chosen"},
        "resolved": {"type": "boolean", "description": "the side is settled"}}),
    "anchors": _open_map(_obj("uwbd.AnchorStats", "ranges of one anchor", {
        "accepted": _COUNT, "deweighted": _COUNT, "rejected": _COUNT,
        "mean_innovation_sigma": _num("mean innovation / σ"),
        "rms_innovation_sigma": _num("RMS innovation / σ")}), "per anchor id"),
    "anchor_findings": {"type": "array", "description": "anchors whose ranges disagree with "
                        "the others' (uwbd.fusion.checks.anchor_consistency)",
                        "items": _obj("uwbd.AnchorFinding", "a suspect anchor", {
                            "anchor": {"type": "integer", "description": "its id"},
                            "bias_m": _num("its ranges' mean error against the others' (m)"),
                            "sigma_m": _num("that mean's σ (m)"),
                            "finding": {"type": "string",
                                        "description": "what a technician should check"}})},
    "mounting_finding": {"type": "string", "description": "what the data say of "
                         "imu.mounting (gravity far from the body's up axis at the start at "
                         "rest, or, with NHC, a vehicle moving sideways in body axes)"},
    "lever_arm_estimate_m": {"type": "array", "items": {"type": "number"},
                             "description": "with [fusion] lever_arm_sigma_m: the lever arm "
                             "the data give (IMU -> antenna, body axes, m)"},
    "anchor_suspected": _obj("uwbd.AnchorSuspected", "the solution-separation test names "
                             "an anchor it has not left out (fault anchor_inconsistent)", {
        "anchor": {"type": "integer", "description": "its id"},
        "separation_m": _num("how far the estimate without its ranges is from the one with "
                             "them (m)"),
        "finding": {"type": "string", "description": "what a technician should check"}}),
    "lever_arm_finding": _obj("uwbd.LeverArmFinding", "the lever-arm test finds the "
                              "configured lever arm off (fault lever_arm_inconsistent)", {
        "key": {"type": "string", "description": "the config key to check: imu.lever_arm_m"},
        "estimate_m": {"type": "array", "items": {"type": "number"},
                       "description": "the lever arm the bank's lever member gives (IMU -> "
                       "antenna, body axes, m)"},
        "finding": {"type": "string", "description": "what a technician should check"}}),
    "heading_observable": {"type": "boolean", "description": "the heading is known"},
    "poses": {"type": "integer", "description": "poses so far"},
    "fusion_counters": _open_map(_COUNT, "filter events by name"),
    "gating_rejections": _open_map(_COUNT, "ranges rejected, by reason"),
    "aligner": _open_map(_COUNT, "time-aligner counters (late, overflow, pending)"),
    "parsers": _open_map({"type": "object", "properties": {}}, "per source: the parser's "
                         "counters and its last error"),
    "sources": _open_map({"type": "object", "properties": {}}, "per source: port, state "
                         "(closed, open, stalled: open but no byte for stall_after_s), opens, "
                         "losses, stalls, bytes, last_error (the daemon)"),
    "zenoh": {"type": "object", "description": "the Zenoh session (the daemon): state (up, "
              "disconnected: no router or peer reached where one is to be, not started), "
              "error, routers and peers reached", "properties": {}},
    "log": {"type": "object", "description": "the log's files and errors (the daemon)",
            "properties": {}},
    "sink_errors": {"type": "array", "items": {"type": "string"},
                    "description": "sinks that failed"},
    "unknown_source_reads": {"type": "integer",
                             "description": "reads from a source the config does not name"},
}, required=("timestamp", "t_ns", "version", "filter", "health", "poses"))

# by schema name, for records logged with a name only (``/truth`` from the simulator, the
# importer and the demo; the status)
SCHEMAS: dict[str, Schema] = {s["title"]: s for s in (
    TRUTH_SCHEMA, STATUS_SCHEMA, FRAME_TRANSFORM_SCHEMA, POSES_IN_FRAME_SCHEMA,
    SCENE_UPDATE_SCHEMA)}
