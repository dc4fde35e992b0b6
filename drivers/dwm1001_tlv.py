"""Decawave/Qorvo DWM1001 binary TLV API: the ``dwm_loc_get`` response (WIRE_FORMATS.md §2.5).

A response is a concatenation of ``Type(1) Length(1) Value(Length)`` records::

    40 01 <err>                 status (0 ok, else error and nothing follows)
    41 0D <x y z int32 mm> <qf> tag position
    49 <L> <cnt> <cnt × 20 B>   distances of a tag: address u16, distance u32 mm, qf u8,
                                anchor x y z int32 mm, anchor position qf u8

TLV has no sync marker and no checksum. The parser synchronises on the status record and
then requires the exact ``loc_get`` structure: ``40 01 00 41 0D`` followed by a ``49`` record
whose length equals ``1 + 20·cnt``. Anything else is skipped a byte at a time. Error replies
(``40 01 <err>``, e.g. ``@\\x01\\x01`` when text reaches a module in TLV mode) are counted in
``stats.device_errors``. Anchor-side distance records (``48``) are skipped and counted as
unknown types: uwbd runs on a tag.
"""

from __future__ import annotations

from drivers.base import BufferedParser, FrameError
from drivers.frames import AnchorRange, UwbRanges
from drivers.layout import Field, Layout

LOC_GET_REQUEST = b"\x0c\x00"
T_STATUS, T_POS, T_ANCHOR_DISTANCES, T_TAG_DISTANCES = 0x40, 0x41, 0x48, 0x49
STATUS_NAMES = {
    0: "ok", 1: "unknown command or broken frame", 2: "internal error",
    3: "invalid parameter", 4: "busy", 5: "operation not permitted", 127: "backhaul",
}
POSITION = Layout((Field("position_m", "i32", 3, 1000), Field("qf", "u8")))
TAG_DISTANCE = Layout((
    Field("address", "u16"), Field("distance_m", "u32", 1, 1000), Field("distance_qf", "u8"),
    Field("anchor_position_m", "i32", 3, 1000), Field("anchor_position_qf", "u8"),
))
ANCHOR_DISTANCE_LEN = 13
MAX_TLV_VALUE = 255
_SYNC = bytes((T_STATUS, 1))
_OK_POS = bytes((T_STATUS, 1, 0, T_POS, POSITION.size))


def encode(frame: UwbRanges) -> bytes:
    """A complete ``loc_get`` response; a frame without position sends zeros with qf 0."""
    pos = {"position_m": frame.tag_position_m or (0.0, 0.0, 0.0), "qf": int(frame.quality or 0)}
    entries = b"".join(
        TAG_DISTANCE.encode({
            "address": r.anchor_id, "distance_m": r.range_m, "distance_qf": int(r.quality or 0),
            "anchor_position_m": r.anchor_position_m or (0.0, 0.0, 0.0),
            "anchor_position_qf": 100,
        })
        for r in frame.ranges
    )
    length = 1 + len(entries)
    if length > MAX_TLV_VALUE:
        raise ValueError(f"{len(frame.ranges)} ranges do not fit one TLV record")
    return (_OK_POS + POSITION.encode(pos)
            + bytes((T_TAG_DISTANCES, length, len(frame.ranges))) + entries)


class Dwm1001TlvParser(BufferedParser):
    """Incremental parser of ``loc_get`` responses into :class:`UwbRanges`."""

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges]:
        self.stats.bytes_in += len(data)
        self._buf += data
        buf, p = self._buf, 0
        out: list[UwbRanges] = []
        while True:
            q = buf.find(_SYNC, p)
            if q < 0:
                # a trailing 0x40 may be the start of the next status record
                keep = len(buf) - 1 if buf.endswith(_SYNC[:1]) else len(buf)
                self._skip(keep - p)
                p = keep
                break
            self._skip(q - p)
            p = q
            used = self._response(buf, p, t_ns, out)
            if used == 0:
                break  # incomplete: wait for more bytes
            if used < 0:
                self._skip(1)
                p += 1
            else:
                p += used
        self._consume(p)
        return out

    def flush(self) -> list[UwbRanges]:
        """End of input: whatever is left cannot complete a response."""
        self._discard_rest()
        return []

    def _skip(self, n: int) -> None:
        self.stats.bytes_skipped += n

    def _response(self, buf: bytearray, p: int, t_ns: int, out: list[UwbRanges]) -> int:
        """Bytes used by the response at ``p``; 0 if it is not complete yet, -1 if invalid."""
        if len(buf) < p + 3:
            return 0
        err = buf[p + 2]
        if err != 0:
            if err not in STATUS_NAMES:
                return -1
            self.stats.device_errors += 1
            self.stats.recent_errors.append(
                FrameError(self._base + p, f"device status {err} ({STATUS_NAMES[err]})"))
            self.stats.bytes_skipped += 3
            return 3
        head = len(_OK_POS)
        if len(buf) < p + head:
            return 0 if _OK_POS.startswith(bytes(buf[p:])) else -1
        if buf[p : p + head] != _OK_POS:
            return -1
        r = p + head + POSITION.size  # start of the distances record
        if len(buf) < r + 3:
            return 0
        kind, length, cnt = buf[r], buf[r + 1], buf[r + 2]
        entry = {T_TAG_DISTANCES: TAG_DISTANCE.size, T_ANCHOR_DISTANCES: ANCHOR_DISTANCE_LEN}
        if kind not in entry or length != 1 + entry[kind] * cnt:
            self.stats.malformed += 1
            self.stats.recent_errors.append(FrameError(
                self._base + r, f"distances record type 0x{kind:02X} length {length} "
                f"does not fit {cnt} entries"))
            return -1
        end = r + 2 + length
        if len(buf) < end:
            return 0
        if kind == T_ANCHOR_DISTANCES:
            self.stats.unknown_types += 1
            self.stats.bytes_skipped += end - p
            return end - p
        pos = POSITION.decode(buf, p + head)
        ranges = []
        for k in range(cnt):
            e = TAG_DISTANCE.decode(buf, r + 3 + k * TAG_DISTANCE.size)
            ranges.append(AnchorRange(e["address"], e["distance_m"], float(e["distance_qf"]),
                                      e["anchor_position_m"]))
        out.append(UwbRanges(t_ns, tuple(ranges), pos["position_m"], float(pos["qf"])))
        self.stats.frames += 1
        return end - p
