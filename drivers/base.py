"""What all parsers share: counters, the error record, and the fixed-frame scanner.

Parsers are sans-I/O: ``feed(data, t_ns)`` takes whatever a read returned and gives back the
frames it completed; they never block, never raise on bad bytes, and keep at most one frame's
worth of unconsumed bytes.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from drivers.frames import Frame

MAX_RECENT_ERRORS = 16


@dataclass(frozen=True, slots=True)
class FrameError:
    """A rejected piece of input: where it was (byte offset in the stream) and why."""

    offset: int
    reason: str

    def __str__(self) -> str:
        return f"byte {self.offset}: {self.reason}"


@dataclass
class ParserStats:
    """Counters every parser keeps instead of raising. ``bytes_skipped`` counts every input
    byte that is not part of an emitted frame (garbage, rejected frames, prompt and echo
    lines); ``dropped`` counts well-formed pieces that could not make a frame (a WitMotion
    cycle without gyro); ``device_errors`` counts error replies from the device itself."""

    frames: int = 0
    bytes_in: int = 0
    bytes_skipped: int = 0
    checksum_errors: int = 0
    unknown_types: int = 0
    malformed: int = 0
    dropped: int = 0
    device_errors: int = 0
    recent_errors: collections.deque[FrameError] = field(
        default_factory=lambda: collections.deque(maxlen=MAX_RECENT_ERRORS)
    )

    def as_dict(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["recent_errors"] = [str(e) for e in self.recent_errors]
        return out


class Parser(Protocol):
    """The driver contract."""

    @property
    def stats(self) -> ParserStats:
        """The parser's counters (an attribute or a property)."""

    def feed(self, data: bytes, t_ns: int = 0) -> Sequence[Frame]:
        """Frames completed by ``data``, which arrived (last byte) at ``t_ns``."""

    def flush(self) -> Sequence[Frame]:
        """End of input: frames still pending, if complete; leftover bytes are counted."""


class BufferedParser:
    """Bookkeeping every parser shares: counters, the bytes not consumed yet, and the
    stream offset of the first of them (``_base``), which error reports cite."""

    def __init__(self) -> None:
        self.stats = ParserStats()
        self._buf = bytearray()
        self._base = 0

    def _consume(self, n: int) -> None:
        """Drop the first ``n`` pending bytes (already accounted for)."""
        self._base += n
        del self._buf[:n]

    def _keep_tail(self, buf: bytes | bytearray, keep_from: int) -> None:
        """``buf`` was the pending bytes plus a read; keep what follows ``keep_from``."""
        self._base += keep_from
        self._buf = bytearray(buf[keep_from:])

    def _discard_rest(self) -> None:
        """End of input: the pending bytes can no longer make a frame."""
        self.stats.bytes_skipped += len(self._buf)
        self._consume(len(self._buf))


@dataclass(frozen=True, slots=True)
class Scan:
    """Result of scanning a buffer for fixed-length frames.

    ``starts``: offsets of accepted frames, in order, non-overlapping. ``keep_from``: where the
    unconsumed tail begins (a possible frame start that is not complete yet).
    ``rejected``: offsets of candidates (header and known type) that failed the checksum and
    lay outside accepted frames; ``unknown``: offsets of headers followed by an unknown type.
    """

    starts: list[int]
    keep_from: int
    skipped: int
    rejected: list[int]
    unknown: list[int]


SMALL_SCAN_BYTES = 512  # below this, a plain loop beats numpy's per-call overhead


def scan_fixed(buf: bytes | bytearray, length: int, header: int, known: frozenset[int]) -> Scan:
    """Find frames ``header, type, payload…, sum8`` of ``length`` bytes in ``buf``.

    Semantics are those of the byte-by-byte resync loop: at each position, accept a frame if
    the header matches, the type byte is in ``known`` and the checksum of bytes
    ``0..length-2`` equals byte ``length-1``, then jump past it; otherwise slide one byte.
    Short buffers (a live read) take that loop literally; long ones (a replay, a capture) test
    every position at once with numpy and walk only overlapping candidates in Python.
    """
    if len(buf) < SMALL_SCAN_BYTES:
        return _scan_loop(buf, length, header, known)
    return _scan_numpy(buf, length, header, _mask(known))


def _scan_loop(buf: bytes | bytearray, length: int, header: int, known: frozenset[int]) -> Scan:
    last = len(buf) - length
    starts: list[int] = []
    rejected: list[int] = []
    unknown: list[int] = []
    p = buf.find(header)
    while 0 <= p <= last:
        if buf[p + 1] not in known:
            unknown.append(p)
        elif sum(buf[p : p + length - 1]) & 0xFF == buf[p + length - 1]:
            starts.append(p)
            p = buf.find(header, p + length)
            continue
        else:
            rejected.append(p)
        p = buf.find(header, p + 1)
    return _finish(buf, length, header, starts=starts, rejected=rejected, unknown=unknown)


def _finish(buf: bytes | bytearray, length: int, header: int, *, starts: list[int],
            rejected: list[int], unknown: list[int]) -> Scan:
    """Where the tail worth keeping starts: the first header no complete frame could follow
    yet (never a negative index: ``find`` would count that from the end)."""
    end = starts[-1] + length if starts else 0
    tail = buf.find(header, max(end, len(buf) - length + 1, 0))
    keep = tail if tail >= 0 else len(buf)
    return Scan(starts, keep, keep - len(starts) * length, rejected, unknown)


@functools.lru_cache(maxsize=16)
def _mask(known: frozenset[int]) -> npt.NDArray[np.bool_]:
    mask = np.zeros(256, dtype=np.bool_)
    mask[list(known)] = True
    return mask


def _scan_numpy(
    buf: bytes | bytearray, length: int, header: int, known_types: npt.NDArray[np.bool_]
) -> Scan:
    arr = np.frombuffer(buf, dtype=np.uint8)
    last = arr.size - length  # last position a complete frame can start at
    if last < 0:
        return _finish(buf, length, header, starts=[], rejected=[], unknown=[])
    heads = np.flatnonzero(arr[: last + 1] == header).astype(np.int64)
    known = known_types[arr[heads + 1]]
    cand = heads[known]
    csum = np.zeros(arr.size + 1, dtype=np.int64)
    np.cumsum(arr, out=csum[1:])
    ok = ((csum[cand + length - 1] - csum[cand]) & 0xFF) == arr[cand + length - 1]
    good = cand[ok]
    if good.size > 1 and np.any(np.diff(good) < length):
        starts_list: list[int] = []
        end = 0
        for p in good.tolist():
            if p >= end:
                starts_list.append(p)
                end = p + length
        starts = np.asarray(starts_list, dtype=np.int64)
    else:
        starts = good
    return _finish(buf, length, header, starts=starts.tolist(),
                   rejected=_outside(cand[~ok], starts, length).tolist(),
                   unknown=_outside(heads[~known], starts, length).tolist())


def _outside(
    pos: npt.NDArray[np.int64], starts: npt.NDArray[np.int64], length: int
) -> npt.NDArray[np.int64]:
    """The positions in ``pos`` that do not lie inside an accepted frame."""
    if pos.size == 0 or starts.size == 0:
        return pos
    idx = np.searchsorted(starts, pos, side="right") - 1
    inside = (idx >= 0) & (pos < starts[np.maximum(idx, 0)] + length)
    return pos[~inside]


def note_scan(stats: ParserStats, scan: Scan, base: int, what: str) -> None:
    """Add a scan's rejections to ``stats``; ``base`` is the stream offset of the buffer."""
    stats.bytes_skipped += scan.skipped
    stats.checksum_errors += len(scan.rejected)
    stats.unknown_types += len(scan.unknown)
    for p in scan.rejected[-MAX_RECENT_ERRORS:]:
        stats.recent_errors.append(FrameError(base + p, f"{what}: checksum mismatch"))
