"""Decawave/Qorvo DWM1001 PANS shell stream ``lec`` (docs/wire-formats.md).

One line per location update::

    DIST,<n>,AN0,<id>,<x>,<y>,<z>,<d>,…,AN<n-1>,…[,POS,<x>,<y>,<z>,<qf>]

``<id>`` is the anchor's 16-bit short address in hex; coordinates and distances are metres
with two decimals; qf is 0-100. A ``lep`` line ``POS,<x>,<y>,<z>,<qf>`` is accepted too and
gives a frame with no ranges.

Lines may end in CR, LF or CRLF. The record may sit anywhere in the line (shell echo such as
``dwm> DIST,…`` or ``lePOS,…``); prompt, echo, banner and blank lines are skipped. A line that
holds ``DIST,`` or ``POS,`` but does not match the grammar exactly (wrong block count, a
truncated block, a bad number) is rejected whole and counted in ``stats.malformed``: a garbled
epoch is worth less than a missing one.
"""

from __future__ import annotations

import re

from drivers.base import BufferedParser, FrameError
from drivers.frames import AnchorRange, UwbRanges

MAX_LINE_BYTES = 1024  # longest plausible line: 15 blocks of ~40 bytes; longer is garbage
MAX_ANCHORS = 15

_NUM = rb"(-?\d{1,6}(?:\.\d{1,6})?)"
_NUM_NC = rb"-?\d{1,6}(?:\.\d{1,6})?"
# capturing block (index, id, x, y, z, d) for findall; non-capturing one inside the line pattern
_BLOCK = rb",AN(\d{1,2}),([0-9A-Fa-f]{4})," + rb",".join([_NUM] * 4)
_BLOCK_NC = rb",AN\d{1,2},[0-9A-Fa-f]{4}(?:," + _NUM_NC + rb"){4}"
_POS = rb"POS," + rb",".join([_NUM] * 3) + rb",(\d{1,3})"
_DIST_RE = re.compile(rb"DIST,(\d{1,2})((?:" + _BLOCK_NC + rb")*)(?:," + _POS + rb")?")
_BLOCK_RE = re.compile(_BLOCK)
_LEP_RE = re.compile(_POS)
_LINE = re.compile(rb"[^\r\n]+")


def encode(frame: UwbRanges) -> bytes:
    """One ``lec`` line, CRLF-terminated; the POS block only when the frame has a position."""
    parts = [f"DIST,{len(frame.ranges)}"]
    for k, r in enumerate(frame.ranges):
        x, y, z = r.anchor_position_m or (0.0, 0.0, 0.0)
        parts.append(f"AN{k},{r.anchor_id:04X},{x:.2f},{y:.2f},{z:.2f},{r.range_m:.2f}")
    if frame.tag_position_m is not None:
        x, y, z = frame.tag_position_m
        parts.append(f"POS,{x:.2f},{y:.2f},{z:.2f},{int(frame.quality or 0)}")
    return (",".join(parts) + "\r\n").encode("ascii")


class Dwm1001ShellParser(BufferedParser):
    """Incremental parser of the DWM1001 shell's ``lec`` (and ``lep``) output."""

    def feed(self, data: bytes, t_ns: int = 0) -> list[UwbRanges]:
        self.stats.bytes_in += len(data)
        self._buf += data
        end = max(self._buf.rfind(b"\n"), self._buf.rfind(b"\r")) + 1
        out: list[UwbRanges] = []
        if end:
            out = self._lines(bytes(self._buf[:end]), t_ns)
            self._consume(end)
        if len(self._buf) > MAX_LINE_BYTES:
            self._reject(self._base, f"line longer than {MAX_LINE_BYTES} bytes")
            self._discard_rest()
        return out

    def flush(self) -> list[UwbRanges]:
        """End of input: a last line without terminator is still a line."""
        out = self._lines(bytes(self._buf), 0)
        self._consume(len(self._buf))
        return out

    def _lines(self, chunk: bytes, t_ns: int) -> list[UwbRanges]:
        """Frames of the complete lines in ``chunk``; line terminators count as part of a line."""
        out = []
        for m in _LINE.finditer(chunk):
            frame, skipped = self._line(m.group(), self._base + m.start(), t_ns)
            self.stats.bytes_skipped += skipped
            if frame is not None:
                out.append(frame)
        self.stats.frames += len(out)
        return out

    def _reject(self, offset: int, reason: str) -> None:
        self.stats.malformed += 1
        self.stats.recent_errors.append(FrameError(offset, reason))

    def _line(self, line: bytes, offset: int, t_ns: int) -> tuple[UwbRanges | None, int]:
        """The frame in one line, if any, and the number of bytes of the line not in it."""
        at = line.rfind(b"DIST,")  # the last one: garbage glued before a line cannot hide it
        if at >= 0:
            frame = self._dist(line, at, t_ns)
        else:
            at = line.rfind(b"POS,")
            if at < 0:
                return None, len(line)  # prompt, echo, banner: not an error
            m = _LEP_RE.fullmatch(line, at)
            frame = None if m is None else UwbRanges(
                t_ns, (), _vec(m.group(1, 2, 3)), float(m.group(4)))
        if frame is None:
            self._reject(offset + at, f"malformed record {line[at : at + 60]!r}")
            return None, len(line)
        return frame, at

    def _dist(self, line: bytes, at: int, t_ns: int) -> UwbRanges | None:
        m = _DIST_RE.fullmatch(line, at)
        if m is None:
            return None
        blocks = _BLOCK_RE.findall(m.group(2))
        n = int(m.group(1))
        if n != len(blocks) or n > MAX_ANCHORS:
            return None
        if any(int(b[0]) != k for k, b in enumerate(blocks)):
            return None
        ranges = tuple(
            AnchorRange(int(b[1], 16), float(b[5]), None, _vec(b[2:5])) for b in blocks)
        if m.group(3) is None:
            return UwbRanges(t_ns, ranges)
        return UwbRanges(t_ns, ranges, _vec(m.group(3, 4, 5)), float(m.group(6)))


def _vec(parts: tuple[bytes, ...]) -> tuple[float, float, float]:
    x, y, z = (float(p) for p in parts)
    return (x, y, z)
