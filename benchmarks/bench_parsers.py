"""Parser throughput: MB/s and frames/s per driver, clean and with 10 % garbage in reads of
``--chunk`` bytes (a capture), and as a serial port returns a device's reports (one report
a read, 30 % of the reads split inside a report: ``uwbd.tools.logtools.SerialReads``).

    python benchmarks/bench_parsers.py [--mb 2] [--chunk 4096] [--repeat 3]

Streams come from the emulator's scenario through the real encoders (the WitMotion sends
accel, gyro, angle and magnetometer packets each cycle); garbage is random bytes rich in
header bytes, in bursts, making up 10 % of the stream. The WitMotion parser is measured on
its C form and on its pure-Python reference, with their ratio. Each figure is the best
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

from drivers import PARSERS, Parser, wit
from drivers.emulator import ENCODERS
from drivers.emulator.scenario import CircleScenario
from uwbd.tools.logtools import SerialReads

LINK_921600_MBPS = 921600 / 10 / 1e6


def reports(driver: str) -> list[bytes]:
    """The scenario's reports as the device sends them, one bytes each."""
    scenario = CircleScenario()
    encode: Callable[[Any], bytes] = ENCODERS[driver]
    if driver == "wit":
        return [encode(dataclasses.replace(f, mag_raw=(210, -5, -390))) for _, f in scenario.imu(5)]
    return [encode(f) for _, f in scenario.uwb(100)]


def clean_stream(driver: str, target_bytes: int) -> tuple[bytes, int, list[bytes]]:
    """Encoded frames of the scenario, repeated to ``target_bytes``; the frame count; the
    stream as a serial port's reads."""
    unit = reports(driver)
    reps = max(1, target_bytes // sum(map(len, unit)))
    shaper = SerialReads(seed=1)
    reads = [data for k in range(reps) for report in unit
             for _, data in shaper.cut(k, report)]
    return b"".join(unit) * reps, len(unit) * reps, reads


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


def measure(make: Callable[[], Parser], reads: list[bytes], repeat: int) -> tuple[float, int]:
    """Best wall time (s) to parse the reads, and frames found."""
    best, frames = float("inf"), 0
    for _ in range(repeat):
        parser = make()
        t0 = time.perf_counter()
        found = 0
        for i, read in enumerate(reads):
            found += len(parser.feed(read, i))
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
    makers: list[tuple[str, Callable[[], Parser]]] = [(d, PARSERS[d]) for d in PARSERS]
    makers.insert(1, ("wit (Python)", wit.WitParser))
    speed: dict[tuple[str, str], float] = {}
    for driver, make in makers:
        clean, n_frames, device_reads = clean_stream(driver.split()[0], int(args.mb * 1e6))
        garbage = with_garbage(clean, 0.10)
        for label, reads in (("clean", chunks(clean, args.chunk)),
                             ("10% garbage", chunks(garbage, args.chunk)),
                             ("device", device_reads)):
            seconds, found = measure(make, reads, args.repeat)
            mbps = sum(map(len, reads)) / seconds / 1e6
            speed[driver, label] = mbps
            print(f"{driver:<12} {label:<11} {mbps:7.2f} {found / seconds:10.0f} "
                  f"{mbps / LINK_921600_MBPS:7.0f} {found:>8}")
            if label != "10% garbage" and found != n_frames:
                raise SystemExit(f"{driver}: parsed {found} of {n_frames} clean frames")
    for label in ("clean", "10% garbage", "device"):
        print(f"wit, C / pure Python, {label}: "
              f"{speed['wit', label] / speed['wit (Python)', label]:.1f}")


def chunks(stream: bytes, size: int) -> list[bytes]:
    return [stream[i:i + size] for i in range(0, len(stream), size)]


if __name__ == "__main__":
    main()
