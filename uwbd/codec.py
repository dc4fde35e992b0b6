"""Frames as JSON-ready dicts: the field names (with units) of the frame dataclasses.

Used by ``uwbd dump`` (:func:`frame_to_dict`: every field, ``null`` where a value is
missing) and by the decoded MCAP channels (:func:`frame_to_json`: a field whose value is
missing is left out, and ``timestamp {sec, nsec}`` is added, so each record fits the
channel's JSON Schema, :mod:`uwbd.logs.foxglove`). Non-finite floats become ``null``, so the
output is strict JSON. Encoding is orjson's (about 15x the standard library's on a pose).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import orjson

from drivers.frames import AnchorPair, AnchorRange, AnchorRanges, Frame, ImuSample, UwbRanges


def frame_to_dict(frame: Frame) -> dict[str, Any]:
    """``{"type": "ImuSample", "t_ns": …, …}`` for any frame."""
    return _plain(_fields(frame))  # type: ignore[no-any-return]


def frame_to_json(frame: Frame) -> bytes:
    """A frame's log record (``/imu``, ``/uwb``) as JSON bytes: ``type``, ``timestamp``, and
    the fields that have a value (:func:`frame_from_dict` reads a missing one as ``None``).
    The decoded log channels take one per frame: an IMU sample's record is made without the
    general walk over the fields."""
    t_ns = frame.t_ns
    kind = type(frame)
    if isinstance(frame, ImuSample):  # most records: its fields by name, in the same order
        imu = {"type": "ImuSample",
               "timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
               "t_ns": t_ns, "acc_mps2": frame.acc_mps2, "gyro_rps": frame.gyro_rps}
        for name in _IMU_OPTIONAL:
            value = getattr(frame, name)
            if value is not None:
                imu[name] = value
        return strict_json(imu)
    out: dict[str, Any] = {"type": kind.__name__,
                           "timestamp": {"sec": t_ns // 1_000_000_000,
                                         "nsec": t_ns % 1_000_000_000}}
    for f in _FIELDS[kind]:
        value = getattr(frame, f)
        if value is None:
            continue
        if f in _ITEM_FIELDS:
            value = [{g: v for g in _ITEM_FIELDS[f] if (v := getattr(r, g)) is not None}
                     for r in value]
        out[f] = value
    return strict_json(out)


_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def strict_json(obj: Any) -> bytes:
    """Any JSON-ready object as compact strict JSON bytes: a non-finite float becomes
    ``null`` (``NaN`` is not JSON, and a Rust or JavaScript parser rejects it); numpy
    numbers are numbers; keys that are not strings are written as the standard library
    writes them. Floats are written shortest-exact: they read back bit for bit. Raises
    ``TypeError`` (``orjson.JSONEncodeError``) for an object JSON has no form for."""
    return orjson.dumps(obj, default=_tuple_subclass, option=_OPTIONS)


def _tuple_subclass(obj: Any) -> Any:
    if isinstance(obj, tuple):  # a NamedTuple: an array, as the standard library writes it
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def _fields(frame: Frame) -> dict[str, Any]:
    # field by field (frames are flat but for ``ranges``): dataclasses.asdict deep-copies
    out: dict[str, Any] = {"type": type(frame).__name__}
    for f in _FIELDS[type(frame)]:
        value = getattr(frame, f)
        if f in _ITEM_FIELDS:  # a tuple of records: each as an object
            value = [{g: getattr(r, g) for g in _ITEM_FIELDS[f]} for r in value]
        out[f] = value
    return out


_FIELDS = {cls: tuple(f.name for f in dataclasses.fields(cls))
           for cls in (ImuSample, UwbRanges, AnchorRanges)}
_IMU_OPTIONAL = _FIELDS[ImuSample][3:]  # after t_ns, acc_mps2, gyro_rps
assert _FIELDS[ImuSample][:3] == ("t_ns", "acc_mps2", "gyro_rps")
_ITEM_FIELDS = {name: tuple(f.name for f in dataclasses.fields(cls))
                for name, cls in (("ranges", AnchorRange), ("pairs", AnchorPair))}


def _plain(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


MAX_T_NS = 2**63 - 1  # int64 nanoseconds: the year 2262


def t_ns_of(value: Any) -> int:
    """A record's time: integer nanoseconds since the Unix epoch, ``0 ≤ t_ns < 2⁶³`` (a float
    that is a whole number in range is taken); ``ValueError`` for anything else (a string,
    null, NaN, 10³⁰, −5)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"t_ns: expected integer nanoseconds, got {value!r}")
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        raise ValueError(f"t_ns: expected integer nanoseconds, got {value!r}")
    if not 0 <= value <= MAX_T_NS:
        raise ValueError(f"t_ns: {value!r} is outside 0 .. 2^63 - 1 ns (1970 .. 2262)")
    return int(value)


def frame_from_dict(d: dict[str, Any]) -> Frame:
    """The inverse of :func:`frame_to_dict` (``null`` back to NaN where a number was)."""
    def vec(v: Any) -> Any:
        return None if v is None else tuple(math.nan if x is None else x for x in v)

    if not isinstance(d, dict):
        raise ValueError(f"not a frame: a JSON {type(d).__name__}, not an object")
    kind = d.get("type")
    if kind == "ImuSample":
        return ImuSample(
            t_ns_of(d["t_ns"]), vec(d["acc_mps2"]), vec(d["gyro_rps"]), d.get("temperature_c"),
            vec(d.get("angle_deg")), vec(d.get("mag_raw")), vec(d.get("quaternion_wire")),
            d.get("device_time_ns"))
    if kind == "UwbRanges":
        ranges = tuple(AnchorRange(int(r["anchor_id"]),
                                   math.nan if r["range_m"] is None else float(r["range_m"]),
                                   r.get("quality"), vec(r.get("anchor_position_m")),
                                   r.get("fp_rssi_dbm"), r.get("rx_rssi_dbm"))
                       for r in d["ranges"])
        return UwbRanges(t_ns_of(d["t_ns"]), ranges, vec(d.get("tag_position_m")), d.get("quality"),
                         vec(d.get("tag_velocity_mps")), vec(d.get("tag_position_error_m")),
                         d.get("tag_id"), d.get("device_time_ms"))
    if kind == "AnchorRanges":
        pairs = tuple(AnchorPair(int(q["anchor_a"]), int(q["anchor_b"]),
                                 math.nan if q["range_m"] is None else float(q["range_m"]))
                      for q in d["pairs"])
        return AnchorRanges(t_ns_of(d["t_ns"]), pairs, d.get("device_time_ms"))
    raise ValueError(f"not a frame: type {kind!r}")
