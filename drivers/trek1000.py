"""Decawave TREK1000 / EVK1000 (DecaRangeRTLS firmware) ASCII range reports: docs/wire-formats.md

One report per line, single spaces, lowercase hex, ``\\r\\n``::

    mc 0f 00000663 000005a3 00000512 000004cb 095f c1 00024c24 a0:0
    mr 0f 000005a4 000004c8 00000436 000003f9 0958 c0 40424042 a0:0
    ma 07 00000000 0000085c 00000659 000006b7 095b 26 00024bed a0:0

Fields, from the one table :data:`REPORT` that both parser and encoder use: the mask of valid
ranges (bit k: range k), four ranges in mm (``%08x`` of a signed int: ``ffffffec`` is -20 mm),
the long-term range count (16 bit), the range sequence number (8 bit), field 9, and the
trailer ``<t|a|l><tag id>:<anchor id>`` (decimal; who reports: tag, anchor or listener).

* ``mc``: range-bias-corrected ranges from the tag to anchors A0..A3; field 9 is the range
  time (a ms tick of the reporting node). Becomes :class:`UwbRanges`, ``anchor_id`` = k for
  each set mask bit k (A0..A3 are 0..3), ``tag_id`` from the trailer, ``device_time_ms`` =
  field 9. Ranges whose bit is clear carry no measurement and yield no :class:`AnchorRange`.
  A negative range stays negative (the gating policy rejects it, counted).
* ``mr``: the same ranges raw (no range-bias correction); field 9 is the TX and RX antenna
  delays, so ``device_time_ms`` is ``None``. The firmware sends one right after each ``mc``.
  **Which one feeds the fusion:** ``mc`` by default (driver ``trek1000``: the bias
  correction depends on the received level, which uwbd cannot model); ``mr`` lines are then
  checked and skipped. Driver ``trek1000-raw`` (``Trek1000Parser(report="mr")``) takes the
  ``mr`` ranges instead and skips the ``mc`` lines: the same device, the same stream.
* ``ma``: anchor-to-anchor ranges, sent by A0 only (trailer always ``a0:0``): mask bit 1 is
  A0-A1 (field 4), bit 2 A0-A2 (field 5), bit 3 A1-A2 (field 6); bit 0's field is unused.
  Becomes :class:`AnchorRanges` (for surveying the anchors; never fused), whichever report
  feeds the fusion; with ``anchor_ranges=False`` the lines are checked and skipped.

Lines may end in CR, LF or CRLF. A record may sit at the end of a line after garbage (the
last ``m[cra] `` in the line is tried); a line holding ``mc ``/``mr ``/``ma `` that does not
match the layout exactly (clone firmwares with 8 ranges, an RSSI word, mask bits above A3,
an ``ma`` not from ``a0:0``) is rejected whole and counted in ``stats.malformed``. Other lines
(``me`` event counters, the handshake replies of §4.5) are skipped without complaint.

:class:`Trek1000Device` is the device side, for the emulator: report lines, and the replies
to the PC handshake (§4.5). The daemon needs no handshake: the device reports on its own, and
the handshake would pause the reports for a second.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from drivers.base import BufferedParser, FrameError
from drivers.frames import AnchorPair, AnchorRange, AnchorRanges, UwbRanges

N_ANCHORS = 4  # A0..A3
MAX_LINE_BYTES = 256  # a report is 65 bytes with one-digit ids; longer is garbage
MAX_ID = 255  # the firmware masks tag ids to 8 bits and anchor ids to 4


@dataclass(frozen=True)
class HexField:
    """One space-separated field: ``digits`` hex digits; ``signed``: two's complement."""

    name: str
    digits: int
    signed: bool = False


# The layout of mc, mr and ma lines alike (§4.2-4.4), between the type and the trailer.
REPORT: tuple[HexField, ...] = (
    HexField("mask", 2),
    *(HexField(f"range{k}_mm", 8, signed=True) for k in range(N_ANCHORS)),
    HexField("count", 4),  # long-term range count, wraps at 16 bits
    HexField("seq", 2),  # range sequence number (ma: A0's anchor-ranging sequence)
    HexField("field9", 8),  # mc, ma: range time, ms tick; mr: TX, RX antenna delay
)
KINDS = (b"mc", b"mr", b"ma")
REPORTERS = b"tal"  # tag, anchor, listener (the PC app accepts l; this firmware sends t, a)
# ma: (mask bit, field holding the range, anchor a, anchor b)
ANCHOR_PAIRS = ((1, "range1_mm", 0, 1), (2, "range2_mm", 0, 2), (3, "range3_mm", 1, 2))
_PAIR_FIELD = {(a, b): (bit, name) for bit, name, a, b in ANCHOR_PAIRS}
DEFAULT_ANTENNA_DELAYS = 0x40424042  # TX and RX, DW1000 time units (the §4.2 example)

_RECORD = re.compile(
    rb"(m[cra]) "
    + b" ".join(rb"([0-9a-fA-F]{%d})" % f.digits for f in REPORT)
    + rb" ([" + REPORTERS + rb"])(\d{1,3}):(\d{1,3})")
_START = re.compile(rb"m[cra] ")
_LINE = re.compile(rb"([^\r\n]*)(?:\r\n|\r|\n|$)")  # a line and its terminator


def _value(f: HexField, text: bytes) -> int:
    v = int(text, 16)
    bits = 4 * f.digits
    return v - (1 << bits) if f.signed and v >> (bits - 1) else v


def _hex(f: HexField, v: int) -> str:
    bits = 4 * f.digits
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if f.signed else (0, (1 << bits) - 1)
    if not lo <= v <= hi:
        raise ValueError(f"{f.name} {v} does not fit {f.digits} hex digits")
    return f"{v & ((1 << bits) - 1):0{f.digits}x}"


def _line(kind: bytes, values: dict[str, int], reporter: str, tag: int, anchor: int) -> bytes:
    if not (0 <= tag <= MAX_ID and 0 <= anchor <= MAX_ID):
        raise ValueError(f"ids {tag}:{anchor} are not within 0..{MAX_ID}")
    fields = " ".join(_hex(f, values.get(f.name, 0)) for f in REPORT)
    return f"{kind.decode()} {fields} {reporter}{tag}:{anchor}\r\n".encode("ascii")


def _mm(range_m: float) -> int:
    return round(range_m * 1000)


def encode(frame: UwbRanges | AnchorRanges, raw_reports: bool = True, count: int = 0,
           seq: int = 0, antenna_delays: int = DEFAULT_ANTENNA_DELAYS, reporter: str = "t",
           anchor_id: int = 0) -> bytes:
    """The lines a tag sends for ``frame``: ``mc`` then (``raw_reports``) ``mr`` with the same
    ranges, trailer ``<reporter><tag id>:<anchor_id>``; an :class:`AnchorRanges` gives one
    ``ma`` line (trailer ``a0:0``).

    Raises ``ValueError`` for what the lines cannot carry: an anchor id outside A0..A3 (or a
    pair other than A0-A1, A0-A2, A1-A2), the same anchor twice, a range beyond int32 mm.
    """
    if isinstance(frame, AnchorRanges):
        return _encode_anchor_ranges(frame, count, seq)
    values = {"count": count, "seq": seq, "field9": frame.device_time_ms or 0, "mask": 0}
    for r in frame.ranges:
        if not 0 <= r.anchor_id < N_ANCHORS:
            raise ValueError(f"anchor id {r.anchor_id} is not one of A0..A{N_ANCHORS - 1}")
        if values["mask"] >> r.anchor_id & 1:
            raise ValueError(f"anchor {r.anchor_id} twice in one epoch")
        values["mask"] |= 1 << r.anchor_id
        values[f"range{r.anchor_id}_mm"] = _mm(r.range_m)
    if reporter.encode() not in (bytes((c,)) for c in REPORTERS):
        raise ValueError(f"reporter {reporter!r} is not one of t, a, l")
    tag = frame.tag_id or 0
    out = _line(b"mc", values, reporter, tag, anchor_id)
    if raw_reports:
        out += _line(b"mr", {**values, "field9": antenna_delays}, reporter, tag, anchor_id)
    return out


def _encode_anchor_ranges(frame: AnchorRanges, count: int, seq: int) -> bytes:
    values = {"count": count, "seq": seq, "field9": frame.device_time_ms or 0, "mask": 0}
    for a, b, range_m in ((q.anchor_a, q.anchor_b, q.range_m) for q in frame.pairs):
        if (a, b) not in _PAIR_FIELD:
            raise ValueError(f"anchors {a}-{b} are not a pair ma reports (A0-A1, A0-A2, A1-A2)")
        bit, name = _PAIR_FIELD[(a, b)]
        if values["mask"] >> bit & 1:
            raise ValueError(f"anchors {a}-{b} twice in one report")
        values["mask"] |= 1 << bit
        values[name] = _mm(range_m)
    return _line(b"ma", values, "a", 0, 0)


def encode_tag_report(frame: UwbRanges | AnchorRanges) -> bytes:
    """What a TREK1000 tag sends for an epoch of any anchor ids: the ranges to A0..A3 (a
    TREK network has four anchors; the others are not heard), ``mc`` then ``mr``."""
    if isinstance(frame, UwbRanges):
        frame = UwbRanges(frame.t_ns, tuple(r for r in frame.ranges
                                            if 0 <= r.anchor_id < N_ANCHORS),
                          tag_id=frame.tag_id, device_time_ms=frame.device_time_ms)
    return encode(frame)


class Trek1000Parser(BufferedParser):
    """Incremental parser of TREK1000 report lines: ``mc`` (or ``mr``) into
    :class:`UwbRanges`, ``ma`` into :class:`AnchorRanges`."""

    def __init__(self, report: Literal["mc", "mr"] = "mc", anchor_ranges: bool = True) -> None:
        super().__init__()
        if report not in ("mc", "mr"):
            raise ValueError(f"report must be 'mc' or 'mr', got {report!r}")
        self.report = report.encode()
        self.anchor_ranges = anchor_ranges  # False: ma lines are checked and skipped

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges | AnchorRanges]:
        self.stats.bytes_in += len(data)
        self._buf += data
        end = max(self._buf.rfind(b"\n"), self._buf.rfind(b"\r")) + 1
        out: list[UwbRanges | AnchorRanges] = []
        if end:
            out = self._lines(bytes(self._buf[:end]), t_ns)
            self._consume(end)
        if len(self._buf) > MAX_LINE_BYTES:
            # no line end for too long: garbage; a record may still begin in the last bytes
            drop = len(self._buf) - MAX_LINE_BYTES // 2
            self.stats.bytes_skipped += drop
            self._consume(drop)
        return out

    def flush(self) -> list[UwbRanges | AnchorRanges]:
        """End of input: a last line without terminator is still a line."""
        out = self._lines(bytes(self._buf), 0)
        self._consume(len(self._buf))
        return out

    def _lines(self, chunk: bytes, t_ns: int) -> list[UwbRanges | AnchorRanges]:
        out: list[UwbRanges | AnchorRanges] = []
        for m in _LINE.finditer(chunk):
            line, offset = m.group(1), self._base + m.start()
            starts = [s.start() for s in _START.finditer(line)]
            frame = None
            if starts:  # else: me lines, handshake replies, blank lines, noise
                at = starts[-1]  # garbage glued before a record cannot hide it
                frame = self._record(line, at, offset, t_ns)
            if frame is None:
                self.stats.bytes_skipped += m.end() - m.start()
            else:
                self.stats.bytes_skipped += at
                out.append(frame)
        self.stats.frames += len(out)
        return out

    def _reject(self, offset: int, reason: str) -> None:
        self.stats.malformed += 1
        self.stats.recent_errors.append(FrameError(offset, reason))

    def _record(self, line: bytes, at: int, offset: int, t_ns: int
                ) -> UwbRanges | AnchorRanges | None:
        m = _RECORD.fullmatch(line, at)
        if m is None:
            self._reject(offset + at, f"malformed report {line[at : at + 80]!r}")
            return None
        kind = m.group(1)
        v = {f.name: _value(f, m.group(k + 2)) for k, f in enumerate(REPORT)}
        reporter, tag, anchor = m.group(len(REPORT) + 2, len(REPORT) + 3, len(REPORT) + 4)
        tag_id, anchor_id = int(tag), int(anchor)
        if tag_id > MAX_ID or anchor_id > MAX_ID:
            self._reject(offset + at, f"ids {tag_id}:{anchor_id} above {MAX_ID}")
            return None
        if kind == b"ma":
            if (reporter, tag_id, anchor_id) != (b"a", 0, 0) or v["mask"] >> (N_ANCHORS):
                self._reject(offset + at, f"ma report not from a0:0 or with mask bits above "
                             f"A{N_ANCHORS - 1}: {line[at : at + 80]!r}")
                return None
            if not self.anchor_ranges:
                return None
            pairs = tuple(AnchorPair(a, b, v[name] / 1000) for bit, name, a, b in ANCHOR_PAIRS
                          if v["mask"] >> bit & 1)
            return AnchorRanges(t_ns, pairs, v["field9"])
        if v["mask"] >> N_ANCHORS:
            self._reject(offset + at, f"mask 0x{v['mask']:02x} has bits above A{N_ANCHORS - 1}")
            return None
        if kind != self.report:
            return None  # the other report of the pair: checked, not used
        ranges = tuple(AnchorRange(k, v[f"range{k}_mm"] / 1000) for k in range(N_ANCHORS)
                       if v["mask"] >> k & 1)
        return UwbRanges(t_ns, ranges, tag_id=tag_id,
                         device_time_ms=v["field9"] if kind == b"mc" else None)


class Trek1000RawParser(Trek1000Parser):
    """The ``trek1000-raw`` driver: ``mr`` (raw) ranges feed the fusion, ``mc`` are skipped."""

    def __init__(self) -> None:
        super().__init__("mr")


# -- the device side (emulator) ---------------------------------------------------------------

VERSION = b"Ver.2.25mx TREK\x00"  # 16 bytes, as the firmware sends it
USB2SPI_VERSION = b"EVB1000 USB2SPI 2.0\x00"
S1_CONFIG = 0x00  # the S1 switch setting the `$` reply carries
PART_ID, LOT_ID = 0x1234ABCD, 0x0001E240
PAUSE_NS = 1_000_000_000  # reports pause this long after a `$` command
COMMAND_LEN = 5  # 'd', three bytes, then '$', '?' or '!'


class Trek1000Device:
    """A TREK1000 tag as the emulator plays it: report lines per epoch, and replies to the
    host's 5-byte commands (§4.5, deca_usb.c):

    * ``d???$`` (the PC app's ``deca$``): ``n`` + 16-byte version + S1 byte + CRLF (20 bytes);
      reports pause for 1 s; if the 4th byte is ``A`` (``decA$``) ``mr`` lines stop;
    * ``d????`` (``deca?``): ``n`` + the USB2SPI version string and a byte; ``mr`` lines on;
    * ``d???!`` (``deca!``): ``n`` + part id (4) + lot id (4) + CRLF.

    ``t_ns`` is the emulator's clock (ns from its start) for both calls.
    """

    def __init__(self) -> None:
        self.raw_reports = True  # sendTWRRawReports: 1 at power-up
        self.paused_until_ns = -1
        self.count = 0
        self.seq = 0
        self._pending = bytearray()

    def report(self, t_ns: int, frame: UwbRanges) -> bytes:
        """The lines for one epoch; empty while reports are paused."""
        ranges = tuple(r for r in frame.ranges if 0 <= r.anchor_id < N_ANCHORS)
        self.count = (self.count + 1) & 0xFFFF
        self.seq = (self.seq + 1) & 0xFF
        if t_ns < self.paused_until_ns:
            return b""
        epoch = UwbRanges(frame.t_ns, ranges, tag_id=frame.tag_id,
                          device_time_ms=(t_ns // 1_000_000) & 0xFFFFFFFF)
        return encode(epoch, self.raw_reports, self.count, self.seq)

    def on_input(self, data: bytes, t_ns: int) -> bytes:
        """The replies to what the host sent (commands may straddle reads)."""
        buf = self._pending
        buf += data
        replies = bytearray()
        p = 0
        while True:
            p = buf.find(b"d", p)
            if p < 0 or len(buf) < p + COMMAND_LEN:
                break
            reply = self._command(bytes(buf[p : p + COMMAND_LEN]), t_ns)
            if reply is None:
                p += 1
                continue
            replies += reply
            p += COMMAND_LEN
        del buf[: len(buf) if p < 0 else p]  # keep a command not complete yet
        return bytes(replies)

    def _command(self, cmd: bytes, t_ns: int) -> bytes | None:
        last = cmd[COMMAND_LEN - 1 :]
        if last == b"$":
            self.paused_until_ns = t_ns + PAUSE_NS
            if cmd[3:4] == b"A":
                self.raw_reports = False
            return b"n" + VERSION + bytes((S1_CONFIG,)) + b"\r\n"
        if last == b"?":
            self.raw_reports = True
            return b"n" + USB2SPI_VERSION + b"\x00"
        if last == b"!":
            return (b"n" + PART_ID.to_bytes(4, "little") + LOT_ID.to_bytes(4, "little")
                    + b"\r\n")
        return None

