"""Decawave/Qorvo DWM1001 binary TLV API: the ``dwm_loc_get`` response (docs/wire-formats.md).

A response is a concatenation of ``Type(1) Length(1) Value(Length)`` records::

    40 01 <err>                 status (0 ok, else error and nothing follows)
    41 0D <x y z int32 mm> <qf> tag position
    49 <L> <cnt> <cnt × 20 B>   distances of a tag: address u16, distance u32 mm, qf u8,
                                anchor x y z int32 mm, anchor position qf u8

TLV has no sync marker and no checksum, so a response leaves the parser only when all of it
is what §2.5 allows: ``40 01 00 41 0D`` followed by a ``49`` (or ``48``) record whose length is
exactly ``1 + 20·cnt`` (``1 + 13·cnt``), every quality factor within 0-100 (the position's,
each distance's and each anchor position's), and no other response starting inside it.

That last rule is the resynchronisation. The device answers each ``loc_get`` in one burst,
so a response that lost bytes on the line is completed by the first bytes of the next one,
and taking it at its word would swallow that good response. The next response's start,
``40 01 00 41 0D`` with a distances record type where one belongs, inside a candidate marks
the candidate as cut short: it is rejected and parsing resumes at that start. A start that
straddles a candidate's end (the cut took 1-4 bytes) can only be seen once the next bytes
arrive; the candidate leaves at once (no waiting for the next poll) and, if the next bytes
show it was cut, it is counted as malformed and parsing goes back to that start.

Anything else is skipped a byte at a time and counted (``stats.malformed`` with the reason
for records that began like a response). Error replies (``40 01 <err>``, e.g. ``@\\x01\\x01``
when text reaches a module in TLV mode) are counted in ``stats.device_errors``. Anchor-side
distance records (``48``) are checked, then skipped and counted as unknown types: uwbd runs on
a tag.
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
ANCHOR_DISTANCE = Layout((
    Field("address", "u64"), Field("distance_m", "u32", 1, 1000), Field("distance_qf", "u8"),
))
MAX_TLV_VALUE = 255
MAX_QF = 100  # every quality factor of the response is a percentage (§2.5, §2.6)
ENTRY_LEN = {T_TAG_DISTANCES: TAG_DISTANCE.size, T_ANCHOR_DISTANCES: ANCHOR_DISTANCE.size}
_SYNC = bytes((T_STATUS, 1))
_OK_POS = bytes((T_STATUS, 1, 0, T_POS, POSITION.size))
_HEAD = len(_OK_POS)
_DIST_AT = _HEAD + POSITION.size  # offset of the distances record in a response
# byte offsets of the quality factors within an entry
_QF_OFFSETS = {T_TAG_DISTANCES: (TAG_DISTANCE.offsets["distance_qf"],
                                 TAG_DISTANCE.offsets["anchor_position_qf"]),
               T_ANCHOR_DISTANCES: (ANCHOR_DISTANCE.offsets["distance_qf"],)}


def encode(frame: UwbRanges) -> bytes:
    """A complete ``loc_get`` response; a frame without position sends zeros with qf 0.

    Raises ``ValueError`` for what a response cannot carry: more ranges than one TLV record
    holds, or a quality outside 0-100.
    """
    qf = int(frame.quality or 0)
    if not 0 <= qf <= MAX_QF:
        raise ValueError(f"position quality {frame.quality} is not within 0..{MAX_QF}")
    pos = {"position_m": frame.tag_position_m or (0.0, 0.0, 0.0), "qf": qf}
    entries = []
    for r in frame.ranges:
        rqf = int(r.quality or 0)
        if not 0 <= rqf <= MAX_QF:
            raise ValueError(f"anchor {r.anchor_id}: quality {r.quality} is not within "
                             f"0..{MAX_QF}")
        entries.append(TAG_DISTANCE.encode({
            "address": r.anchor_id, "distance_m": r.range_m, "distance_qf": rqf,
            "anchor_position_m": r.anchor_position_m or (0.0, 0.0, 0.0),
            "anchor_position_qf": MAX_QF,
        }))
    length = 1 + sum(len(e) for e in entries)
    if length > MAX_TLV_VALUE:
        raise ValueError(f"{len(frame.ranges)} ranges do not fit one TLV record")
    return (_OK_POS + POSITION.encode(pos)
            + bytes((T_TAG_DISTANCES, length, len(frame.ranges))) + b"".join(entries))


def _starts_response(buf: bytearray, s: int) -> bool:
    """Does a ``loc_get`` response start at ``s``: its 5-byte head, and a distances record
    type where one belongs (if that byte is here yet)?"""
    if buf[s : s + _HEAD] != _OK_POS:
        return False
    return len(buf) <= s + _DIST_AT or buf[s + _DIST_AT] in ENTRY_LEN


class Dwm1001TlvParser(BufferedParser):
    """Incremental parser of ``loc_get`` responses into :class:`UwbRanges`."""

    def __init__(self) -> None:
        super().__init__()
        # end (in the buffer) of the last response emitted while its last bytes might still
        # turn out to be the start of the next one; None when that is settled
        self._emitted_end: int | None = None

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges]:
        self.stats.bytes_in += len(data)
        self._buf += data
        buf, p = self._buf, 0
        out: list[UwbRanges] = []
        while True:
            if self._emitted_end is not None:
                resume = self._look_back(buf, self._emitted_end)
                if resume is None:
                    p = self._emitted_end
                    break  # undecided: the bytes after it are not here yet
                p = resume
                self._emitted_end = None
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
        if self._emitted_end is not None:
            keep = max(self._emitted_end - (_HEAD - 1), 0)  # the bytes a start may use
            self._emitted_end -= keep
            self._consume(keep)
        else:
            self._consume(p)
        return out

    def flush(self) -> list[UwbRanges]:
        """End of input: whatever is left cannot complete a response."""
        if self._emitted_end is not None:
            self._consume(self._emitted_end)  # part of the last response: not skipped
            self._emitted_end = None
        self._discard_rest()
        return []

    def _skip(self, n: int) -> None:
        self.stats.bytes_skipped += n

    def _reject(self, p: int, reason: str) -> int:
        self.stats.malformed += 1
        self.stats.recent_errors.append(FrameError(self._base + p, reason))
        return -1

    def _look_back(self, buf: bytearray, end: int) -> int | None:
        """Where to go on after the response emitted last, which ends at ``end``: back to
        where the next one starts if that is in its last bytes (it was cut short), else
        ``end``; None while the bytes that would tell are not here yet."""
        for s in range(max(end - (_HEAD - 1), 0), end):
            have = buf[s : s + _HEAD]
            if not _OK_POS.startswith(have):
                continue
            if len(have) < _HEAD:
                return None
            if _starts_response(buf, s):
                self._reject(s, "the response before this byte was cut short: the next "
                             "one starts inside it")
                return s
        return end

    def _inner_start(self, buf: bytearray, p: int, end: int) -> int:
        """Where a response starts inside ``buf[p + 1 : end]`` (-1: nowhere)."""
        s = buf.find(_OK_POS, p + 1, end + _HEAD - 1)
        while 0 <= s < end:
            if _starts_response(buf, s):
                return s
            s = buf.find(_OK_POS, s + 1, end + _HEAD - 1)
        return -1

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
        if len(buf) < p + _HEAD:
            return 0 if _OK_POS.startswith(bytes(buf[p:])) else -1
        if buf[p : p + _HEAD] != _OK_POS:
            return -1
        r = p + _DIST_AT  # start of the distances record
        if len(buf) < r + 3:
            return 0
        if buf[r - 1] > MAX_QF:
            return self._reject(p + _HEAD, f"position quality {buf[r - 1]} above {MAX_QF}")
        kind, length, cnt = buf[r], buf[r + 1], buf[r + 2]
        if kind not in ENTRY_LEN or length != 1 + ENTRY_LEN[kind] * cnt:
            return self._reject(r, f"distances record type 0x{kind:02X} length {length} "
                                f"does not fit {cnt} entries")
        end = r + 2 + length
        inner = self._inner_start(buf, p, min(end, len(buf)))
        if inner >= 0:
            return self._reject(p, f"cut short: the next response starts at byte "
                                f"{self._base + inner}")
        if len(buf) < end:
            return 0
        size = ENTRY_LEN[kind]
        for k in range(cnt):
            e = r + 3 + k * size
            for off in _QF_OFFSETS[kind]:
                if buf[e + off] > MAX_QF:
                    return self._reject(e + off, f"entry {k}: quality {buf[e + off]} above "
                                        f"{MAX_QF}")
        if len(buf) < end + _HEAD - 1:
            self._emitted_end = end  # its last bytes may yet prove to be the next start
        if kind == T_ANCHOR_DISTANCES:
            self.stats.unknown_types += 1
            self.stats.bytes_skipped += end - p
            return end - p
        pos = POSITION.decode(buf, p + _HEAD)
        ranges = []
        for k in range(cnt):
            d = TAG_DISTANCE.decode(buf, r + 3 + k * TAG_DISTANCE.size)
            ranges.append(AnchorRange(d["address"], d["distance_m"], float(d["distance_qf"]),
                                      d["anchor_position_m"]))
        out.append(UwbRanges(t_ns, tuple(ranges), pos["position_m"], float(pos["qf"])))
        self.stats.frames += 1
        return end - p
