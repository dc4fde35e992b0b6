"""Nooploop LinkTrack NLink ``NodeFrame2`` (docs/wire-formats.md), variable length.

``55 04 <length u16>``, a fixed part of 119 bytes (:data:`NODE_FRAME2`: role, id, system time,
eop, position, velocity, the tag IMU, local time, voltage, and the count N of node records),
N records of 13 bytes (:data:`NODE2_RECORD`: the remote node's role and id, distance,
first-path and total RSSI, measurement time) and a checksum, the low byte of the sum of all
the bytes before it; ``length = 119 + 13·N + 1``.

Each record becomes an :class:`AnchorRange` whose ``anchor_id`` is the remote node's id
(0..255; in LinkTrack's LP mode a tag's records are its anchors), with ``fp_rssi_dbm`` and
``rx_rssi_dbm`` as sent and ``quality`` derived from them (:func:`nlos_quality`): the gap
``rx - fp`` is small on a direct path and grows when the first path is attenuated (NLOS), so
the quality is 100 up to 6 dB and falls 10 per dB beyond, to 0 at 16 dB; the filter scales the
range variance by ``100/quality`` (at most 10×). The tag's own position, velocity, eop and
system time travel with the ranges, as in TagFrame0. The tag IMU is emitted as an
:class:`ImuSample` only with ``emit_imu=True`` (as :class:`drivers.nlink.NlinkParser`).

Resynchronisation (§3.4): find ``55``; a mark other than ``04`` drops one byte and counts an
unknown type (TagFrame0 ``55 01`` included: driver ``nlink`` reads those); a length that no
N fits (below 120, above 119 + 13·255 + 1, not 120 + 13·N) drops one byte and counts as
malformed, as does an N at offset 118 that disagrees with the length, which is seen before the
whole frame has to arrive; a failed checksum drops one byte and counts a checksum error.
"""

from __future__ import annotations

from typing import Any

from drivers.base import BufferedParser, FrameError
from drivers.frames import AnchorRange, ImuSample, UwbRanges
from drivers.layout import Field, Layout, sum8
from drivers.nlink import HEADER, ROLE_TAG

MARK_NODE_FRAME2 = 0x04
ROLE_ANCHOR = 1
RSSI_DIV = -2  # raw u8 / -2 -> dBm (§3.1)

NODE_FRAME2 = Layout((
    Field("header", "u8"), Field("mark", "u8"), Field("frame_length", "u16"),
    Field("role", "u8"), Field("id", "u8"),  # role before id in this frame
    Field("system_time_ms", "u32"),
    Field("eop_m", "u8", 3, 100),
    Field("pos_m", "i24", 3, 1000),
    Field("vel_mps", "i24", 3, 10000),
    Field("reserved1", "pad", 9),
    Field("imu_gyro", "f32", 3),
    Field("imu_acc_mps2", "f32", 3),
    Field("reserved2", "pad", 12),
    Field("angle_deg", "i16", 3, 100),
    Field("quaternion", "f32", 4),
    Field("reserved3", "pad", 4),
    Field("local_time_ms", "u32"),
    Field("reserved4", "pad", 10),
    Field("voltage_v", "u16", 1, 1000),
    Field("valid_node_count", "u8"),
))
NODE2_RECORD = Layout((
    Field("role", "u8"), Field("id", "u8"),
    Field("dis_m", "i24", 1, 1000),
    Field("fp_rssi_dbm", "u8", 1, RSSI_DIV),
    Field("rx_rssi_dbm", "u8", 1, RSSI_DIV),
    Field("system_time_ms", "u32"),
    Field("reserved", "pad", 2),
))
FIXED_LEN = NODE_FRAME2.size
assert FIXED_LEN == 119 and NODE2_RECORD.size == 13
MAX_NODES = 255
MIN_LEN = FIXED_LEN + 1
MAX_LEN = FIXED_LEN + NODE2_RECORD.size * MAX_NODES + 1
_COUNT_AT = NODE_FRAME2.offsets["valid_node_count"]

LOS_GAP_DB = 6.0  # rx - fp up to this: a direct path
QUALITY_PER_DB = 10.0  # quality lost per dB of gap beyond it
DEFAULT_RX_RSSI_DBM = -80.0  # what the encoder sends for a range without RSSIs
DEFAULT_FP_RSSI_DBM = -82.0


def nlos_quality(fp_rssi_dbm: float, rx_rssi_dbm: float) -> float:
    """A range's quality (0-100) from its first-path and total received power.

    ``rx - fp`` at most 6 dB (a direct path: most energy arrives first) gives 100; each dB
    beyond takes 10, so 10 dB gives 60 (range variance ×1.7) and 16 dB or more gives 0 (the
    filter's largest de-weighting, ×10). Exact on the wire's 0.5 dB grid.
    """
    gap = rx_rssi_dbm - fp_rssi_dbm
    return min(100.0, max(0.0, 100.0 - QUALITY_PER_DB * (gap - LOS_GAP_DB)))


def encode(frame: UwbRanges, imu: ImuSample | None = None) -> bytes:
    """A NodeFrame2 carrying ``frame`` (and the tag IMU ``imu``, if given).

    A range without RSSIs is sent with -82/-80 dBm (a direct path, quality 100); a range's
    ``quality`` is not sent, the parser derives it from the RSSIs. Raises ``ValueError`` for an
    anchor id outside 0..255 or more than 255 ranges.
    """
    if len(frame.ranges) > MAX_NODES:
        raise ValueError(f"{len(frame.ranges)} ranges: a NodeFrame2 holds at most {MAX_NODES}")
    time_ms = frame.device_time_ms or 0
    records = []
    for r in frame.ranges:
        if not 0 <= r.anchor_id <= 0xFF:
            raise ValueError(f"anchor id {r.anchor_id} is not a NodeFrame2 node id 0..255")
        records.append(NODE2_RECORD.encode({
            "role": ROLE_ANCHOR, "id": r.anchor_id, "dis_m": r.range_m,
            "fp_rssi_dbm": DEFAULT_FP_RSSI_DBM if r.fp_rssi_dbm is None else r.fp_rssi_dbm,
            "rx_rssi_dbm": DEFAULT_RX_RSSI_DBM if r.rx_rssi_dbm is None else r.rx_rssi_dbm,
            "system_time_ms": time_ms,
        }))
    values: dict[str, object] = {
        "header": HEADER, "mark": MARK_NODE_FRAME2,
        "frame_length": MIN_LEN + NODE2_RECORD.size * len(records),
        "role": ROLE_TAG, "id": frame.tag_id or 0, "system_time_ms": time_ms,
        "eop_m": frame.tag_position_error_m or (0.0, 0.0, 0.0),
        "pos_m": frame.tag_position_m or (0.0, 0.0, 0.0),
        "vel_mps": frame.tag_velocity_mps or (0.0, 0.0, 0.0),
        "valid_node_count": len(records),
    }
    if imu is not None:
        values.update({
            "imu_gyro": imu.gyro_rps, "imu_acc_mps2": imu.acc_mps2,
            "angle_deg": imu.angle_deg or (0.0, 0.0, 0.0),
            "quaternion": imu.quaternion_wire or (0.0, 0.0, 0.0, 0.0),
        })
    body = NODE_FRAME2.encode(values) + b"".join(records)
    return bytes(body + bytes((sum8(body),)))


def _length_ok(length: int) -> bool:
    return MIN_LEN <= length <= MAX_LEN and (length - MIN_LEN) % NODE2_RECORD.size == 0


class NlinkNode2Parser(BufferedParser):
    """Incremental parser of an NLink byte stream (NodeFrame2) into :class:`UwbRanges`."""

    def __init__(self, emit_imu: bool = False) -> None:
        super().__init__()
        self.emit_imu = emit_imu

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges | ImuSample]:
        self.stats.bytes_in += len(data)
        self._buf += data
        buf, p = self._buf, 0
        out: list[UwbRanges | ImuSample] = []
        while True:
            q = buf.find(HEADER, p)
            if q < 0:
                q = len(buf)
            self.stats.bytes_skipped += q - p
            p = q
            used = self._frame(buf, p, t_ns, out)
            if used == 0:
                break  # incomplete (or nothing left): wait for more bytes
            if used < 0:
                self.stats.bytes_skipped += 1
                p += 1
            else:
                p += used
        self._consume(p)
        return out

    def flush(self) -> list[UwbRanges | ImuSample]:
        self._discard_rest()
        return []

    def _error(self, p: int, reason: str) -> int:
        self.stats.recent_errors.append(FrameError(self._base + p, reason))
        return -1

    def _frame(self, buf: bytearray, p: int, t_ns: int, out: list[UwbRanges | ImuSample]
               ) -> int:
        """Bytes used by the frame at ``p``; 0 if not complete yet, -1 if not a frame."""
        if len(buf) < p + 2:
            return 0
        if buf[p + 1] != MARK_NODE_FRAME2:
            self.stats.unknown_types += 1
            return -1
        if len(buf) < p + 4:
            return 0
        length = buf[p + 2] | buf[p + 3] << 8
        if not _length_ok(length):
            self.stats.malformed += 1
            return self._error(p, f"NodeFrame2: length {length} fits no node count")
        if len(buf) > p + _COUNT_AT and MIN_LEN + NODE2_RECORD.size * buf[p + _COUNT_AT] \
                != length:
            self.stats.malformed += 1
            return self._error(p, f"NodeFrame2: length {length} does not fit "
                               f"{buf[p + _COUNT_AT]} nodes")
        if len(buf) < p + length:
            return 0
        if sum8(memoryview(buf)[p : p + length - 1]) != buf[p + length - 1]:
            self.stats.checksum_errors += 1
            return self._error(p, "NodeFrame2: checksum mismatch")
        self._emit(NODE_FRAME2.decode(buf, p), buf, p, t_ns, out)
        self.stats.frames += 1
        return length

    def _emit(self, f: dict[str, Any], buf: bytearray, p: int, t_ns: int,
              out: list[UwbRanges | ImuSample]) -> None:
        ranges = []
        for k in range(f["valid_node_count"]):
            r = NODE2_RECORD.decode(buf, p + FIXED_LEN + k * NODE2_RECORD.size)
            fp, rx = r["fp_rssi_dbm"], r["rx_rssi_dbm"]
            ranges.append(AnchorRange(r["id"], r["dis_m"], nlos_quality(fp, rx),
                                      fp_rssi_dbm=fp, rx_rssi_dbm=rx))
        out.append(UwbRanges(
            t_ns=t_ns, ranges=tuple(ranges),
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
