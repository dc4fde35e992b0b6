"""Each frame of a read its own time: the frames one read of a port holds, spread back
from the read's time by the source's learned sample period.

A read's receive time is exact only for its last frame; when one read holds several frames
of a source (the port was read late, or batched: ``ports.SerialSource.batch_reads``), the
earlier ones arrived about one sample period apart before it. Without this they share one
time and the filter must drop all but one. The period is learned per source from
successive reads: the time between their last frames over the frames the later one holds,
as a ratio of sums that fade by ``FADE`` a read (a read that holds a cycle and a part of
the next is stamped up to a period late, and a mean of per-read ratios would be biased by
the reads that complete one frame where two periods passed). A source's frames are always
later than the one before: a frame a WitMotion cycle's wrap lets go a read late carries an
earlier read's time, and is put 1 ns after its predecessor; the frames of a first read (a
backlog, no period known) are 1 ns apart.

A read is stamped when it returns, and a batched port returns when its VMIN-th byte has
come: most often inside the next report, whose first bytes came a gap after the last whole
frame. Where the source's baud is known, the bytes a read carries past its last whole frame
are counted (``carry``: what came in, less the frames out at the source's bytes a frame,
learned as the rounded ratio of slowly faded sums), and the last frame is put back by their
time on the wire and the gap before them (the period less a frame's time on the wire). A
read that ends on a report's end carries nothing and keeps its time: a report a read is as
before, to the bit. Deterministic: the daemon
(:class:`~uwbd.service.pipeline.Pipeline`), replay and the offline tools' decoding
(:func:`~uwbd.tools.logtools.load_recording`) give a log's reads the same times.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from drivers import AnchorRanges, Frame
from drivers.frames import retimed
from uwbd.config import SourceConfig

# the drivers whose ports are batched (IMU only; reports of one size, which the carry needs)
BATCHED_DRIVERS = frozenset({"wit"})
FADE = 0.875  # of the sample period's sums, a read
BYTES_FADE = 0.99  # of the bytes-a-frame sums, a read (slow: the ratio is rounded)


class SampleTimes:
    """The sources' learned sample periods and their last frames' times (see module doc)."""

    def __init__(self, baud: Mapping[str, int] | None = None) -> None:
        """``baud``: each batched source's (8N1: ten bits a byte; :func:`batched_bauds`)."""
        self.period_ns: dict[str, int] = {}  # per source, the learned sample period
        self._sums: dict[str, tuple[float, float]] = {}  # its time spanned, its frames
        self._last_ns: dict[str, int] = {}  # the time of its last frame
        self._byte_ns = {name: 1e10 / b for name, b in (baud or {}).items() if b > 0}
        self._bytes: dict[str, tuple[float, float]] = {}  # bytes in, frames out
        self._carry: dict[str, int] = {}  # bytes past the last whole frame

    def spread(self, source: str, frames: Sequence[Frame], read_bytes: int = 0
               ) -> Sequence[Frame]:
        """The frames of one read of ``source`` (``read_bytes`` long), each with a time of
        its own."""
        survey = [f for f in frames if f.__class__ is AnchorRanges] if frames else []
        if survey:  # anchor-to-anchor reports are not samples of the source: keep their times
            samples = [f for f in frames if f.__class__ is not AnchorRanges]
            return [*self.spread(source, samples, read_bytes), *survey] if samples else survey
        back_ns = self._carried(source, len(frames), read_bytes) if read_bytes else 0
        if len(frames) < 2:  # most reads: no frame, or one (what the branches below do)
            if frames:
                t_ns, floor = frames[0].t_ns - back_ns, self._last_ns.get(source)
                self._learn(source, t_ns, 1)
                if floor is not None and t_ns <= floor:  # stamped with an earlier read's time
                    t_ns = self._last_ns[source] = floor + 1
                if t_ns != frames[0].t_ns:
                    return [retimed(frames[0], t_ns)]
            return frames
        n, last_ns, floor = len(frames), frames[-1].t_ns - back_ns, self._last_ns.get(source)
        period = self.period_ns.get(source)  # from the reads before this one
        self._learn(source, last_ns, n)
        if period is None:  # not known yet: this read's own estimate, or for the first read
            period = self.period_ns.get(source, 0)  # (a backlog) 1 ns apart, in order
        spread = []  # spread back from the last
        for k, f in enumerate(frames):
            t = min(last_ns - (n - 1 - k) * period, f.t_ns)  # never later than its own stamp,
            if floor is not None and t <= floor:  # but after the frame before it
                t = floor + 1
            floor = t
            spread.append(retimed(f, t))
        self._last_ns[source] = spread[-1].t_ns
        return spread

    def _carried(self, source: str, count: int, read_bytes: int) -> int:
        """How long before the read's time its last whole frame ended (see module doc)."""
        byte_ns = self._byte_ns.get(source)
        if byte_ns is None:
            return 0
        bytes_in, frames_out = self._bytes.get(source, (0.0, 0.0))
        bytes_in, frames_out = BYTES_FADE * bytes_in + read_bytes, BYTES_FADE * frames_out + count
        self._bytes[source] = bytes_in, frames_out
        if frames_out < 1.0:
            return 0
        frame_bytes = max(round(bytes_in / frames_out), 1)
        carry = self._carry.get(source, 0) + read_bytes - count * frame_bytes
        carry = carry % frame_bytes if carry > 0 else 0  # (garbage, a lost byte: resynced)
        self._carry[source] = carry
        period = self.period_ns.get(source)
        if not count or not carry or period is None:
            return 0
        return int(carry * byte_ns + max(period - frame_bytes * byte_ns, 0.0))

    def _learn(self, source: str, t_ns: int, count: int) -> None:
        """A read that held ``count`` frames of ``source``, the last at ``t_ns``."""
        previous = self._last_ns.get(source)
        if previous is not None and t_ns > previous:
            span_ns, frames = self._sums.get(source, (0.0, 0.0))
            span_ns, frames = FADE * span_ns + (t_ns - previous), FADE * frames + count
            self._sums[source] = span_ns, frames
            self.period_ns[source] = int(span_ns / frames)
        self._last_ns[source] = t_ns


def batched_bauds(sources: Iterable[SourceConfig], prefix: str = "") -> dict[str, int]:
    """The bauds of the sources whose ports are batched, by name (``prefix`` before it: a
    log's ``/raw/`` topics)."""
    return {prefix + s.name: s.baud for s in sources if s.driver in BATCHED_DRIVERS}
