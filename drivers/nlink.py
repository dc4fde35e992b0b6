"""Nooploop LinkTrack NLink protocol, ``TagFrame0`` (docs/wire-formats.md).

A fixed 128-byte frame ``55 01 …`` ending in the low byte of the sum of the 127 bytes before
it. Distances to anchors 0..7 sit in ``dis_m``; 0 means "no range" and yields no
:class:`AnchorRange`, so the ``anchor_id`` of a range is its slot 0..7. The tag's own position
solution, velocity and estimated position error (``eop``) travel with the ranges.

The tag also carries an IMU. It is emitted as an :class:`ImuSample` only when the parser is
built with ``emit_imu=True`` (gyro assumed rad/s; the quaternion in wire order), so that a
tag's IMU never enters the fusion as a second IMU by accident.

Other NLink frames (other function marks after 0x55) are skipped and counted as unknown types.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from drivers import accel
from drivers.base import BufferedParser, note_scan, scan_fixed
from drivers.frames import AnchorRange, ImuSample, UwbRanges
from drivers.layout import Field, Layout, sum8

HEADER, MARK_TAG_FRAME0 = 0x55, 0x01
N_SLOTS = 8
ROLE_TAG = 2

TAG_FRAME0 = Layout((
    Field("header", "u8"), Field("mark", "u8"),
    Field("id", "u8"), Field("role", "u8"),  # id before role in this frame
    Field("pos_m", "i24", 3, 1000),
    Field("vel_mps", "i24", 3, 10000),
    Field("dis_m", "i24", N_SLOTS, 1000),
    Field("imu_gyro", "f32", 3),
    Field("imu_acc_mps2", "f32", 3),
    Field("reserved1", "pad", 12),
    Field("angle_deg", "i16", 3, 100),
    Field("quaternion", "f32", 4),
    Field("reserved2", "pad", 4),
    Field("local_time_ms", "u32"),
    Field("system_time_ms", "u32"),
    Field("reserved3", "pad", 1),
    Field("eop_m", "u8", 3, 100),
    Field("voltage_v", "u16", 1, 1000),
    Field("reserved4", "pad", 5),
    Field("checksum", "u8"),
))
FRAME_LEN = TAG_FRAME0.size
assert FRAME_LEN == 128

_KNOWN = frozenset({MARK_TAG_FRAME0})
# what accel's tag_frame0 (drivers/_frames.c) is handed: the fields it fills, by name, in the
# order it fills them (every field of each dataclass), and the frame's layout from TAG_FRAME0
# (the one table): its size, header and mark, the offsets it reads, then their divisors
_FILLS = {UwbRanges: ("t_ns", "ranges", "tag_position_m", "quality", "tag_velocity_mps",
                      "tag_position_error_m", "tag_id", "device_time_ms"),
          AnchorRange: ("anchor_id", "range_m", "quality", "fp_rssi_dbm", "rx_rssi_dbm",
                        "anchor_position_m")}
assert all(set(names) == {f.name for f in dataclasses.fields(cls)}
           for cls, names in _FILLS.items()), "a frame field accel.tag_frame0 does not fill"
_READS = ("id", "pos_m", "vel_mps", "dis_m", "system_time_ms", "eop_m")
_FAST_PARTS = (
    *(x for cls, names in _FILLS.items()
      for x in (cls, tuple(cls.__dict__[name] for name in names))),
    (TAG_FRAME0.size, HEADER, MARK_TAG_FRAME0, *(TAG_FRAME0.offsets[name] for name in _READS),
     *(float(next(f.div or 1 for f in TAG_FRAME0.fields if f.name == name))
       for name in ("pos_m", "vel_mps", "dis_m", "eop_m"))))


def encode(frame: UwbRanges, imu: ImuSample | None = None) -> bytes:
    """A TagFrame0 carrying ``frame`` (and the tag IMU ``imu``, if given).

    Raises ``ValueError`` for an anchor id outside the 8 slots or a zero range, neither of
    which the frame can carry.
    """
    dis = [0.0] * N_SLOTS
    for r in frame.ranges:
        if not 0 <= r.anchor_id < N_SLOTS:
            raise ValueError(f"anchor id {r.anchor_id} is not a TagFrame0 slot 0..{N_SLOTS - 1}")
        if round(r.range_m * 1000) == 0:
            raise ValueError(f"anchor {r.anchor_id}: a zero range means 'missing' on the wire")
        dis[r.anchor_id] = r.range_m
    values: dict[str, object] = {
        "header": HEADER, "mark": MARK_TAG_FRAME0, "id": frame.tag_id or 0, "role": ROLE_TAG,
        "pos_m": frame.tag_position_m or (0.0, 0.0, 0.0),
        "vel_mps": frame.tag_velocity_mps or (0.0, 0.0, 0.0),
        "dis_m": dis,
        "eop_m": frame.tag_position_error_m or (0.0, 0.0, 0.0),
        "system_time_ms": frame.device_time_ms or 0,
    }
    if imu is not None:
        values.update({
            "imu_gyro": imu.gyro_rps, "imu_acc_mps2": imu.acc_mps2,
            "angle_deg": imu.angle_deg or (0.0, 0.0, 0.0),
            "quaternion": imu.quaternion_wire or (0.0, 0.0, 0.0, 0.0),
        })
    body = TAG_FRAME0.encode(values)
    body[-1] = sum8(body[:-1])
    return bytes(body)


class NlinkParser(BufferedParser):
    """Incremental parser of an NLink byte stream (TagFrame0) into :class:`UwbRanges`."""

    def __init__(self, emit_imu: bool = False) -> None:
        super().__init__()
        self.emit_imu = emit_imu

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges | ImuSample]:
        fast = accel.frames
        if fast is not None and not self._buf and not self.emit_imu and len(data) == FRAME_LEN:
            # the common read, one whole frame, in one call (None: not that; below then)
            frame = fast.tag_frame0(data, t_ns, _FAST_PARTS)
            if frame is not None:
                stats = self.stats
                stats.bytes_in += FRAME_LEN
                stats.frames += 1
                self._base += FRAME_LEN
                self._buf = bytearray()  # as _keep_tail leaves it
                return [frame]
        self.stats.bytes_in += len(data)
        buf = self._buf + data if self._buf else data
        scan = scan_fixed(buf, FRAME_LEN, HEADER, _KNOWN)
        note_scan(self.stats, scan, self._base, "nlink TagFrame0")
        out: list[UwbRanges | ImuSample] = []
        for p in scan.starts:
            self._frame(TAG_FRAME0.decode(buf, p), t_ns, out)
        self.stats.frames += len(scan.starts)
        self._keep_tail(buf, scan.keep_from)
        return out

    def flush(self) -> list[UwbRanges | ImuSample]:
        self._discard_rest()
        return []

    def _frame(self, f: dict[str, Any], t_ns: int, out: list[UwbRanges | ImuSample]) -> None:
        dis: tuple[float, ...] = f["dis_m"]
        ranges = tuple(AnchorRange(k, d) for k, d in enumerate(dis) if d != 0.0)
        out.append(UwbRanges(
            t_ns=t_ns, ranges=ranges,
            tag_position_m=f["pos_m"],
            tag_velocity_mps=f["vel_mps"],
            tag_position_error_m=f["eop_m"],
            tag_id=f["id"],
            device_time_ms=f["system_time_ms"],
        ))
        if self.emit_imu:
            out.append(ImuSample(
                t_ns=t_ns,
                acc_mps2=f["imu_acc_mps2"],
                gyro_rps=f["imu_gyro"],
                angle_deg=f["angle_deg"],
                quaternion_wire=f["quaternion"],
                device_time_ns=f["system_time_ms"] * 1_000_000,
            ))
