"""The time-aligner: frames from several sources in, one timestamp-ordered stream out.

Frames carry the receive time of their last byte (``t_ns``). Reads from different ports are
handled one after another, so frames can reach the aligner slightly out of order. It holds
each frame until the *latest arrival time it has seen* is ``wait_ns`` past it, then releases
the held frames in timestamp order; a frame older than one already released is late: it is
dropped and counted. The clock is the data's own, not the wall clock, so a replay that feeds
the logged reads in log order makes exactly the same decisions as the live run did.

With ``wait_ns = 0`` (the default for low latency) frames pass straight through and only
genuinely out-of-order ones are dropped. The buffer is bounded by ``max_pending``.
"""

from __future__ import annotations

import heapq
import itertools

from drivers.frames import Frame


class Aligner:
    def __init__(self, wait_ns: int = 0, max_pending: int = 10_000) -> None:
        if wait_ns < 0 or max_pending < 1:
            raise ValueError("wait_ns must be >= 0 and max_pending >= 1")
        self.wait_ns = wait_ns
        self.max_pending = max_pending
        self.late = 0  # dropped: older than a frame already released
        self.overflow = 0  # released early because the buffer was full
        self._heap: list[tuple[int, int, Frame]] = []
        self._order = itertools.count()
        self._clock_ns = -(2**63)
        self._released_ns = -(2**63)

    def push(self, frame: Frame) -> list[Frame]:
        """Take one frame; returns the frames that may go to the filter now, in order."""
        t_ns = frame.t_ns
        if t_ns < self._released_ns:
            self.late += 1
            return []
        if self.wait_ns == 0 and not self._heap:  # what the heap would do, without it
            self._clock_ns = self._released_ns = t_ns  # t_ns >= released >= any clock seen
            return [frame]
        self._clock_ns = max(self._clock_ns, t_ns)
        heapq.heappush(self._heap, (frame.t_ns, next(self._order), frame))
        out = []
        while self._heap and (self._heap[0][0] <= self._clock_ns - self.wait_ns
                              or len(self._heap) > self.max_pending):
            if len(self._heap) > self.max_pending:
                self.overflow += 1
            out.append(self._pop())
        return out

    def flush(self) -> list[Frame]:
        """End of input: everything still held, in order."""
        return [self._pop() for _ in range(len(self._heap))]

    def _pop(self) -> Frame:
        t_ns, _, frame = heapq.heappop(self._heap)
        self._released_ns = t_ns
        return frame

    def stats(self) -> dict[str, int]:
        return {"late": self.late, "overflow": self.overflow, "pending": len(self._heap)}
