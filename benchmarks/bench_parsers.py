"""Parser throughput: MB/s and frames/s per driver, clean and with 10 % garbage.

    python benchmarks/bench_parsers.py [--mb 2] [--chunk 4096] [--repeat 3]

Streams come from the emulator's scenario through the real encoders; garbage is random
bytes rich in header bytes, in bursts, making up 10 % of the stream. Each figure is the best
of ``--repeat`` runs, all measured side by side in this one process. The reference is a
saturated 921600-baud link: 92.16 kB/s.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers import PARSERS
from drivers.emulator import ENCODERS
from drivers.emulator.scenario import CircleScenario

LINK_921600_MBPS = 921600 / 10 / 1e6


def clean_stream(driver: str, target_bytes: int) -> tuple[bytes, int]:
    """Encoded frames of the scenario, repeated to ``target_bytes``; and the frame count."""
    scenario = CircleScenario()
    encode: Callable[[Any], bytes] = ENCODERS[driver]
    frames: list[Any]
    if driver == "wit":
        frames = [dataclasses.replace(f, angle_deg=(1.0, 2.0, 3.0)) for _, f in scenario.imu(5)]
    else:
        frames = [f for _, f in scenario.uwb(100)]
    unit = b"".join(encode(f) for f in frames)
    reps = max(1, target_bytes // len(unit))
    return unit * reps, len(frames) * reps


def with_garbage(stream: bytes, fraction: float, seed: int = 1) -> bytes:
    """Insert random bursts (a third of their bytes 0x55) so garbage is ``fraction`` of it."""
    rng = np.random.default_rng(seed)
    n_garbage = int(len(stream) * fraction / (1 - fraction))
    out, pos, burst = [], 0, 64
    cuts = np.sort(rng.integers(0, len(stream), size=max(1, n_garbage // burst)))
    for cut in cuts.tolist():
        out.append(stream[pos:cut])
        junk = rng.integers(0, 256, size=burst, dtype=np.uint8)
        junk[rng.random(burst) < 0.33] = 0x55
        out.append(junk.tobytes())
        pos = cut
    out.append(stream[pos:])
    return b"".join(out)


def measure(driver: str, stream: bytes, chunk: int, repeat: int) -> tuple[float, int]:
    """Best wall time (s) to parse ``stream`` in reads of ``chunk`` bytes, and frames found."""
    best, frames = float("inf"), 0
    for _ in range(repeat):
        parser = PARSERS[driver]()
        t0 = time.perf_counter()
        found = 0
        for i in range(0, len(stream), chunk):
            found += len(parser.feed(stream[i : i + chunk], i))
        found += len(parser.flush())
        best = min(best, time.perf_counter() - t0)
        frames = found
    return best, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=2.0, help="stream size per case, MB")
    ap.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"parser throughput, {args.mb} MB per case, reads of {args.chunk} B, "
          f"best of {args.repeat}; x-link = multiple of a saturated 921600-baud link")
    print(f"{'driver':<12} {'stream':<11} {'MB/s':>7} {'frames/s':>10} {'x-link':>7} "
          f"{'frames':>8}")
    for driver in PARSERS:
        clean, n_frames = clean_stream(driver, int(args.mb * 1e6))
        for label, stream in (("clean", clean), ("10% garbage", with_garbage(clean, 0.10))):
            seconds, found = measure(driver, stream, args.chunk, args.repeat)
            mbps = len(stream) / seconds / 1e6
            print(f"{driver:<12} {label:<11} {mbps:7.2f} {found / seconds:10.0f} "
                  f"{mbps / LINK_921600_MBPS:7.0f} {found:>8}")
            if label == "clean" and found != n_frames:
                raise SystemExit(f"{driver}: parsed {found} of {n_frames} clean frames")


if __name__ == "__main__":
    main()
