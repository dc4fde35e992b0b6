"""WitMotion "0x55" standard protocol (JY901, WT901, HWT901B, HWT905…): docs/wire-formats.md

Every packet is 11 bytes: ``0x55, type, D0, D1, D2, D3, sum8`` with D0..D3 int16 LE.

**Sample rule.** The device sends one *cycle* of packets per output period, in increasing type
order (0x50 time, 0x51 accel, 0x52 gyro, 0x53 angle, 0x54 mag, 0x59 quaternion; which ones is
set by its RSW register). The parser groups packets into cycles and emits one
:class:`~drivers.frames.ImuSample` per cycle that holds both accel and gyro:

* a cycle ends when a packet arrives whose type is not greater than the previous one (the type
  number wraps), or when the cycle's *closing type* arrives;
* the closing type is learned from the stream: the highest type of the last complete cycle.
  In steady state the sample therefore leaves with the cycle's last packet, without waiting
  for the next cycle; until learned, or when the closing packet is lost, it leaves on the wrap;
* a cycle without accel or without gyro is counted in ``stats.dropped`` and not emitted;
* if a packet follows the closing type without a wrap, the device's packet set has grown:
  that orphan is dropped and the closing type is learned again;
* ``t_ns`` is the receive time of the cycle's last packet; 0x5F register read-backs are not
  part of any cycle.

Units out: m/s² (the protocol's g is taken as standard gravity 9.80665 m/s²), rad/s, °C, deg.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Mapping
from typing import Any

from drivers import accel
from drivers.base import BufferedParser, FrameError, ParserStats, Scan, note_scan, scan_fixed
from drivers.frames import ImuSample
from drivers.layout import Field, Layout, sum8

HEADER = 0x55
PACKET_LEN = 11
STANDARD_GRAVITY_MPS2 = 9.80665

TIME, ACC, GYRO, ANGLE, MAG, PORT, QUAT, READBACK = 0x50, 0x51, 0x52, 0x53, 0x54, 0x55, 0x59, 0x5F
KNOWN_TYPES = frozenset(range(0x50, 0x5B)) | {READBACK}

ACC_DIV = 32768 / (16 * STANDARD_GRAVITY_MPS2)  # raw / 32768 * 16 g  -> m/s²
GYRO_DIV = 32768 / (2000 * math.pi / 180)  # raw / 32768 * 2000 °/s -> rad/s
ANGLE_DIV = 32768 / 180  # raw / 32768 * 180 -> deg
TEMP_DIV = 100  # raw / 100 -> °C
QUAT_DIV = 32768

# One table per packet type: the 8 bytes D0..D3 after header and type.
PAYLOADS: dict[int, Layout] = {
    TIME: Layout((
        Field("YY", "u8"), Field("MM", "u8"), Field("DD", "u8"),
        Field("hh", "u8"), Field("mm", "u8"), Field("ss", "u8"), Field("ms", "u16"),
    )),
    ACC: Layout((Field("acc_mps2", "i16", 3, ACC_DIV),
                 Field("temperature_c", "i16", 1, TEMP_DIV))),
    GYRO: Layout((Field("gyro_rps", "i16", 3, GYRO_DIV),
                  Field("temperature_c", "i16", 1, TEMP_DIV))),
    ANGLE: Layout((Field("angle_deg", "i16", 3, ANGLE_DIV), Field("version", "u16"))),
    MAG: Layout((Field("mag_raw", "i16", 3), Field("temperature_c", "i16", 1, TEMP_DIV))),
    QUAT: Layout((Field("quaternion_wire", "i16", 4, QUAT_DIV),)),
}
_PAYLOAD_OFFSET = 2



def device_time_ns(fields: dict[str, int]) -> int | None:
    """Calendar time of a 0x50 packet as Unix-epoch ns (the device clock is taken as UTC)."""
    try:
        stamp = dt.datetime(
            2000 + fields["YY"], fields["MM"], fields["DD"], fields["hh"], fields["mm"],
            fields["ss"], tzinfo=dt.timezone.utc,
        )
    except ValueError:
        return None  # an unset clock sends zeros, which is no date
    return int(stamp.timestamp()) * 1_000_000_000 + fields["ms"] * 1_000_000


def _time_fields(t_ns: int) -> dict[str, int]:
    stamp = dt.datetime.fromtimestamp(t_ns // 1_000_000_000, tz=dt.timezone.utc)
    return {
        "YY": stamp.year - 2000, "MM": stamp.month, "DD": stamp.day, "hh": stamp.hour,
        "mm": stamp.minute, "ss": stamp.second, "ms": (t_ns // 1_000_000) % 1000,
    }


def encode_packet(ptype: int, fields: Mapping[str, object]) -> bytes:
    """One 11-byte packet of ``ptype`` from its payload fields."""
    body = bytearray((HEADER, ptype)) + PAYLOADS[ptype].encode(fields)
    return bytes(body + bytes((sum8(body),)))


def encode(sample: ImuSample) -> bytes:
    """The packets of one cycle, in device order, for the parts ``sample`` holds.

    The temperature goes into the accel and gyro (and mag) packets, as the device sends it.
    """
    temp = {"temperature_c": sample.temperature_c or 0.0}
    out = []
    if sample.device_time_ns is not None:
        out.append(encode_packet(TIME, _time_fields(sample.device_time_ns)))
    out.append(encode_packet(ACC, {"acc_mps2": sample.acc_mps2, **temp}))
    out.append(encode_packet(GYRO, {"gyro_rps": sample.gyro_rps, **temp}))
    if sample.angle_deg is not None:
        out.append(encode_packet(ANGLE, {"angle_deg": sample.angle_deg}))
    if sample.mag_raw is not None:
        out.append(encode_packet(MAG, {"mag_raw": sample.mag_raw, **temp}))
    if sample.quaternion_wire is not None:
        out.append(encode_packet(QUAT, {"quaternion_wire": sample.quaternion_wire}))
    return b"".join(out)


class WitParser(BufferedParser):
    """Incremental parser of a WitMotion byte stream into :class:`ImuSample` (see module doc)."""

    def __init__(self) -> None:
        super().__init__()
        self._cycle: dict[str, Any] = {}
        self._last_type = -1
        self._cycle_t_ns = 0
        self._cycle_max = -1
        self._closing_type = -1

    def feed(self, data: bytes, t_ns: int = 0) -> list[ImuSample]:
        self.stats.bytes_in += len(data)
        buf = self._buf + data if self._buf else data
        scan: Scan = scan_fixed(buf, PACKET_LEN, HEADER, KNOWN_TYPES)
        note_scan(self.stats, scan, self._base, "wit packet")
        out: list[ImuSample] = []
        for p in scan.starts:
            self._packet(buf[p + 1], buf, p + _PAYLOAD_OFFSET, t_ns, out)
        self._keep_tail(buf, scan.keep_from)
        return out

    def flush(self) -> list[ImuSample]:
        """End of input: emit the pending cycle, if complete, and count leftover bytes."""
        out: list[ImuSample] = []
        self._close(out)
        self._discard_rest()
        return out

    def _packet(self, ptype: int, buf: bytes | bytearray, at: int, t_ns: int,
                out: list[ImuSample]) -> None:
        if ptype == READBACK:
            return
        if ptype <= self._last_type:  # the type number wrapped: a new cycle begins
            if self._cycle_max >= 0:
                self._close(out)
        elif self._last_type == self._closing_type >= 0 and self._cycle_max < 0:
            # a packet after the learned closing type, before any wrap: the device's cycle
            # grew (its packet set was changed). Relearn; the orphan packet is dropped.
            self._closing_type = -1
        self._last_type = ptype
        self._cycle_max = max(self._cycle_max, ptype)
        self._cycle_t_ns = t_ns
        layout = PAYLOADS.get(ptype)
        if layout is not None:
            fields = layout.decode(buf, at)
            if ptype == TIME:
                self._cycle["device_time_ns"] = device_time_ns(fields)
            else:
                self._cycle.update(fields)
        if ptype == self._closing_type:
            self._close(out)
            self._last_type = ptype  # so the next packet tells a wrap from a longer cycle

    def _close(self, out: list[ImuSample]) -> None:
        cycle = self._cycle
        if "acc_mps2" in cycle and "gyro_rps" in cycle:
            self._closing_type = self._cycle_max
            out.append(ImuSample(
                t_ns=self._cycle_t_ns,
                acc_mps2=cycle["acc_mps2"],
                gyro_rps=cycle["gyro_rps"],
                temperature_c=cycle.get("temperature_c"),
                angle_deg=cycle.get("angle_deg"),
                mag_raw=cycle.get("mag_raw"),
                quaternion_wire=cycle.get("quaternion_wire"),
                device_time_ns=cycle.get("device_time_ns"),
            ))
            self.stats.frames += 1
        elif cycle or self._cycle_max >= 0:
            self.stats.dropped += 1
        self._cycle = {}
        self._last_type = -1
        self._cycle_max = -1


def _divisor(ptype: int, name: str) -> float:
    (div,) = {f.div for f in PAYLOADS[ptype].fields if f.name == name}
    assert div is not None
    return div


# what the C parser scales each field by: the table above's
_DIVISORS = (_divisor(ACC, "acc_mps2"), _divisor(GYRO, "gyro_rps"),
             _divisor(ACC, "temperature_c"), _divisor(ANGLE, "angle_deg"),
             _divisor(QUAT, "quaternion_wire"))
assert {_divisor(p, "temperature_c") for p in (ACC, GYRO, MAG)} == {_DIVISORS[2]}
# what it makes its samples of: ImuSample's slots, in the order drivers/_wit.c fills them
_FILLS = ("t_ns", "acc_mps2", "gyro_rps", "temperature_c", "angle_deg", "mag_raw",
          "quaternion_wire", "device_time_ns")
assert set(_FILLS) == {f.name for f in dataclasses.fields(ImuSample)}, \
    "an ImuSample field the C parser does not fill"
_SLOTS = tuple(getattr(ImuSample, name) for name in _FILLS)
# and the packet's layout, from the tables above: header, length, the temperature's byte in
# the payload, the packet types it decodes, and every type it knows
(_TEMPERATURE_AT,) = {PAYLOADS[p].offsets["temperature_c"] for p in (ACC, GYRO, MAG)}
_LAYOUT = (HEADER, PACKET_LEN, _TEMPERATURE_AT, TIME, ACC, GYRO, ANGLE, MAG, QUAT, READBACK,
           tuple(sorted(KNOWN_TYPES)))


class CWitParser:
    """:class:`WitParser` on the C stream parser (``drivers/_wit.c``): the same samples and
    counters from the same bytes (tested against it), in one call per read."""

    def __init__(self) -> None:
        assert accel.frames is not None
        self._stream = accel.frames.WitStream(ImuSample, _SLOTS, _DIVISORS, _LAYOUT)
        self._stats = ParserStats()

    def feed(self, data: bytes, t_ns: int = 0) -> list[ImuSample]:
        samples: list[ImuSample] = self._stream.feed(data, t_ns)
        return samples

    def flush(self) -> list[ImuSample]:
        samples: list[ImuSample] = self._stream.flush()
        return samples

    @property
    def _buf(self) -> bytes:
        """The bytes held for the next read (BufferedParser's name)."""
        pending: bytes = self._stream.pending
        return pending

    @property
    def stats(self) -> ParserStats:
        stats = self._stats
        (stats.frames, stats.bytes_in, stats.bytes_skipped, stats.checksum_errors,
         stats.unknown_types, stats.dropped) = self._stream.counts
        stats.recent_errors.extend(FrameError(offset, "wit packet: checksum mismatch")
                                   for offset in self._stream.errors())
        return stats


def new_parser() -> WitParser | CWitParser:
    """The C parser where it is built (and ``UWBD_PURE_PYTHON`` unset), else the reference."""
    return WitParser() if accel.frames is None else CWitParser()
