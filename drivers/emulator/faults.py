"""Fault injection: turns a device's timed frames into the timed byte chunks of a bad link.

Every fault is drawn from one seeded generator per device, so a faulty run is reproducible.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

# (time offset ns, payload); payload None marks "unplug now", b"" marks "plug back now".
Event = tuple[int, bytes | None]
UNPLUG: None = None
REPLUG = b""


@dataclass(frozen=True)
class Window:
    """A time window ``[at_s, at_s + duration_s)`` from the start of the run."""

    at_s: float
    duration_s: float

    def contains(self, t_ns: int) -> bool:
        return self.at_s * 1e9 <= t_ns < (self.at_s + self.duration_s) * 1e9

    @classmethod
    def parse(cls, text: str) -> Window:
        """``"AT:DURATION"`` in seconds, e.g. ``"5:2"``."""
        try:
            at, duration = (float(x) for x in text.split(":"))
        except ValueError as err:
            raise ValueError(f"expected AT:DURATION in seconds, got {text!r}") from err
        if at < 0 or duration <= 0:
            raise ValueError(f"window {text!r}: need AT >= 0 and DURATION > 0")
        return cls(at, duration)


@dataclass(frozen=True)
class Faults:
    """What goes wrong on one emulated link.

    * ``garbage_rate_hz``: mean rate of garbage bursts (Poisson), each 1..``garbage_max_bytes``
      random bytes, with a fair share of the header byte 0x55 (and ``55 55`` pairs);
    * ``split``: write each frame in random chunks, spaced by their time on the wire;
    * ``corrupt_prob``: per frame, one payload byte flipped (a checksum error for binary
      formats, an unparsable line for text);
    * ``drop_prob``: per frame, the frame is not sent;
    * ``stalls``: windows in which the device sends nothing;
    * ``unplugs``: windows in which the port does not exist (closed and re-created).
    """

    garbage_rate_hz: float = 0.0
    garbage_max_bytes: int = 32
    split: bool = False
    corrupt_prob: float = 0.0
    drop_prob: float = 0.0
    stalls: tuple[Window, ...] = ()
    unplugs: tuple[Window, ...] = ()

    def __post_init__(self) -> None:
        for name in ("corrupt_prob", "drop_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be within [0, 1]")
        if self.garbage_rate_hz < 0 or self.garbage_max_bytes < 1:
            raise ValueError("garbage_rate_hz must be >= 0 and garbage_max_bytes >= 1")


@dataclass
class FaultCounts:
    frames: int = 0
    dropped: int = 0
    corrupted: int = 0
    stalled: int = 0
    garbage_bursts: int = 0
    garbage_bytes: int = 0
    unplugs: int = 0


def inject(
    frames: Iterable[tuple[int, bytes]], faults: Faults, baud: int, seed: int,
    counts: FaultCounts,
) -> Iterator[Event]:
    """The byte events of ``frames`` (time offset ns, encoded bytes) under ``faults``."""
    rng = np.random.default_rng(seed)
    byte_ns = round(10e9 / baud)  # 8N1: ten bit-times per byte
    next_garbage_ns = _next_arrival(rng, 0, faults.garbage_rate_hz)
    edges = sorted({round(w.at_s * 1e9) for w in faults.unplugs}
                   | {round((w.at_s + w.duration_s) * 1e9) for w in faults.unplugs})
    done_edges = 0
    for t_ns, data in frames:
        while done_edges < len(edges) and edges[done_edges] <= t_ns:
            edge = edges[done_edges]
            unplugged = any(w.contains(edge) for w in faults.unplugs)
            if unplugged:
                counts.unplugs += 1
            yield edge, (UNPLUG if unplugged else REPLUG)
            done_edges += 1
        while next_garbage_ns <= t_ns:
            burst = _garbage(rng, faults.garbage_max_bytes)
            counts.garbage_bursts += 1
            counts.garbage_bytes += len(burst)
            yield next_garbage_ns, burst
            next_garbage_ns = _next_arrival(rng, next_garbage_ns, faults.garbage_rate_hz)
        if any(w.contains(t_ns) for w in faults.stalls):
            counts.stalled += 1
            continue
        if faults.drop_prob and rng.random() < faults.drop_prob:
            counts.dropped += 1
            continue
        if faults.corrupt_prob and rng.random() < faults.corrupt_prob and len(data) > 3:
            flipped = bytearray(data)
            flipped[int(rng.integers(1, len(data) - 2))] ^= 0x80
            data = bytes(flipped)  # noqa: PLW2901 - the frame as it leaves the faulty link
            counts.corrupted += 1
        counts.frames += 1
        if not faults.split:
            yield t_ns, data
            continue
        cuts = sorted(set(rng.integers(1, len(data), size=min(3, len(data) - 1)).tolist()))
        for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True):
            yield t_ns + a * byte_ns, data[a:b]


def _next_arrival(rng: np.random.Generator, after_ns: int, rate_hz: float) -> int:
    if rate_hz <= 0:
        return 2**63 - 1
    return after_ns + max(1, round(rng.exponential(1e9 / rate_hz)))


def _garbage(rng: np.random.Generator, max_bytes: int) -> bytes:
    n = int(rng.integers(1, max_bytes + 1))
    burst = bytearray(rng.integers(0, 256, size=n, dtype=np.uint8).tobytes())
    for i in np.flatnonzero(rng.random(n) < 0.15).tolist():
        burst[i] = 0x55  # header bytes make resynchronisation work for its living
    return bytes(burst)

