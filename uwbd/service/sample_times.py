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
backlog, no period known) are 1 ns apart. Deterministic: the daemon
(:class:`~uwbd.service.pipeline.Pipeline`), replay and the offline tools' decoding
(:func:`~uwbd.tools.logtools.load_recording`) give a log's reads the same times.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers import AnchorRanges, Frame
from drivers.frames import retimed

FADE = 0.875  # of the sample period's sums, a read


class SampleTimes:
    """The sources' learned sample periods and their last frames' times (see module doc)."""

    def __init__(self) -> None:
        self.period_ns: dict[str, int] = {}  # per source, the learned sample period
        self._sums: dict[str, tuple[float, float]] = {}  # its time spanned, its frames
        self._last_ns: dict[str, int] = {}  # the time of its last frame

    def spread(self, source: str, frames: Sequence[Frame]) -> Sequence[Frame]:
        """The frames of one read of ``source``, each with a time of its own."""
        if len(frames) < 2:  # most reads: no frame, or one (what the branches below do)
            if frames and frames[0].__class__ is not AnchorRanges:
                t_ns, floor = frames[0].t_ns, self._last_ns.get(source)
                self._learn(source, t_ns, 1)
                if floor is not None and t_ns <= floor:  # stamped with an earlier read's time
                    self._last_ns[source] = floor + 1
                    return [retimed(frames[0], floor + 1)]
            return frames
        survey = [f for f in frames if isinstance(f, AnchorRanges)]
        if survey:  # anchor-to-anchor reports are not samples of the source: keep their times
            frames = [f for f in frames if not isinstance(f, AnchorRanges)]
            return [*self.spread(source, frames), *survey] if frames else survey
        n, last_ns, floor = len(frames), frames[-1].t_ns, self._last_ns.get(source)
        period = self.period_ns.get(source)  # from the reads before this one
        self._learn(source, last_ns, n)
        if period is None:  # not known yet: this read's own estimate, or for the first read
            period = self.period_ns.get(source, 0)  # (a backlog) 1 ns apart, in order
        spread = []  # spread back from the last
        for k, f in enumerate(frames):
            t = min(f.t_ns - (n - 1 - k) * period, f.t_ns)  # never later than its own stamp,
            if floor is not None and t <= floor:  # but after the frame before it
                t = floor + 1
            floor = t
            spread.append(retimed(f, t))
        self._last_ns[source] = spread[-1].t_ns
        return spread

    def _learn(self, source: str, t_ns: int, count: int) -> None:
        """A read that held ``count`` frames of ``source``, the last at ``t_ns``."""
        previous = self._last_ns.get(source)
        if previous is not None and t_ns > previous:
            span_ns, frames = self._sums.get(source, (0.0, 0.0))
            span_ns, frames = FADE * span_ns + (t_ns - previous), FADE * frames + count
            self._sums[source] = span_ns, frames
            self.period_ns[source] = int(span_ns / frames)
        self._last_ns[source] = t_ns
