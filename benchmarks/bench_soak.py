"""A long daemon run: does anything grow?

    python benchmarks/bench_soak.py [--minutes 120] [--warmup-minutes 10] [--every-s 30]
                                    [--smaps-minutes 5 20] [--trace-frames 1]

The daemon's own loop (``uwbd.service.daemon.run``, as ``uwbd run`` runs it) in this
process, fed by the emulator (a 200 Hz WitMotion and a 10 Hz Nooploop tag over
pseudo-terminals, its threads in this process too, steady), logging to a temporary folder
with rotation, Zenoh on a unix socket, no scouting. Every ``--every-s`` seconds: the RSS
(``/proc/self/statm``), the Python heap (``tracemalloc``, ``--trace-frames`` deep; 0: off)
and glibc's heap (held from the OS and in use, ``mallinfo2``). Printed after the warm-up: both
slopes (MB/min, least squares over the samples after it), and the ten allocation sites that
grew most between the first sample after the warm-up and the last (that snapshot is taken
before the sample: its own memory, several MB that malloc keeps, was the RSS step
earlier soaks saw at the end of the warm-up). Target: RSS slope
≤ 0.01 MB/min over two hours. At each of ``--smaps-minutes`` the resident size of every
mapping (``/proc/self/smaps``, grouped by file, anonymous ones as ``[anon]``, the heap
as ``[heap]``) is taken, and the mappings that grew most between the first and the last
are printed: where a step of the RSS lives, a library's pages or anonymous memory.

The process's CPU (user + system, of one core) is printed at the end. A soak that needs a
whole core has fallen behind the devices (the emulator runs in this process, and deep
``tracemalloc`` stacks slow every allocation several times): its memory then holds a
backlog, not the daemon's steady state, and the run says so.
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import os
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np

from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from uwbd.config import SourceConfig, parse, to_toml
from uwbd.service.daemon import run

PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 1e6


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE_MB


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def malloc_mb() -> tuple[float, float]:
    """glibc's heap: (held from the OS, in use) in MB, or NaN off glibc.

    RSS that grows while "in use" stays flat is the allocator keeping freed memory (its
    arenas), not a leak; "in use" growing is live C or Python memory."""
    try:
        info = ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return float("nan"), float("nan")
    info.restype = _MallInfo2
    m = info()
    return (m.arena + m.hblkhd) / 1e6, (m.uordblks + m.hblkhd) / 1e6


def mapped_kb() -> dict[str, int]:
    """Resident kB per mapping (its file, ``[heap]``, ``[stack]``..., or ``[anon]``)."""
    sizes: dict[str, int] = {}
    name = "[anon]"
    with open("/proc/self/smaps") as f:
        for line in f:
            head, _, rest = line.partition(" ")
            if "-" in head and not head.endswith(":"):  # a mapping's first line
                fields = line.split()
                name = fields[5] if len(fields) > 5 else "[anon]"
            elif head == "Rss:":
                sizes[name] = sizes.get(name, 0) + int(rest.split()[0])
    return sizes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=120.0)
    ap.add_argument("--warmup-minutes", type=float, default=10.0)
    ap.add_argument("--every-s", type=float, default=30.0)
    ap.add_argument("--smaps-minutes", type=float, nargs="*", default=[5.0, 20.0])
    ap.add_argument("--trace-frames", type=int, default=1)
    args = ap.parse_args()
    if args.trace_frames > 0:
        tracemalloc.start(args.trace_frames)
    with tempfile.TemporaryDirectory(prefix="uwbd-soak-") as tmp:
        work = Path(tmp)
        devices = [DeviceSpec("imu", "wit", Faults()), DeviceSpec("uwb", "nlink", Faults())]
        scenario = CircleScenario(seed=1)
        with Emulator(devices, scenario, None, work) as emu:
            sources = [SourceConfig(d.name, d.driver, emu.ports[d.name].path, 921600)
                       for d in devices]
            text = to_toml(sources, dict(enumerate(scenario.anchors_m)), ((1, 0, 0),
                           (0, 1, 0), (0, 0, 1)), (0.0, 0.0, 0.0))
            text += (f'\n[zenoh]\nprefix = "uwbd/soak"\nlisten = ["unixsock-stream/'
                     f'{work / "z.sock"}"]\nmulticast_scouting = false\n'
                     '\n[log]\nrotate_minutes = 10\n')
            config = parse(text, "soak config")
            samples: list[tuple[float, float, float]] = []
            snapshots: list[tracemalloc.Snapshot] = []
            maps: list[tuple[float, dict[str, int]]] = []
            due = sorted(args.smaps_minutes)
            stop = threading.Event()
            started = time.monotonic()
            warm_s = args.warmup_minutes * 60

            def sample() -> None:
                while not stop.wait(args.every_s):
                    t = time.monotonic() - started
                    if t >= warm_s and not snapshots and tracemalloc.is_tracing():
                        # before the sample: a snapshot's own memory (several MB of traces,
                        # freed but kept by malloc) is a step of the RSS, not the daemon's
                        snapshots.append(tracemalloc.take_snapshot())
                    heap = tracemalloc.get_traced_memory()[0] / 1e6
                    samples.append((t, rss_mb(), heap))
                    while due and t >= due[0] * 60:
                        due.pop(0)
                        maps.append((t / 60, mapped_kb()))
                    held, used = malloc_mb()
                    print(f"  {t / 60:6.1f} min  RSS {samples[-1][1]:6.1f} MB  Python heap "
                          f"{heap:6.1f} MB  malloc held {held:6.1f} / in use {used:6.1f} MB",
                          flush=True)

            sampler = threading.Thread(target=sample, daemon=True)
            emu.start()
            sampler.start()
            cpu_before = os.times()
            pipeline = asyncio.run(run(config, work / "logs", args.minutes * 60, summary_s=600))
            cpu = os.times()
            stop.set()
            if tracemalloc.is_tracing():
                snapshots.append(tracemalloc.take_snapshot())
    busy = ((cpu.user - cpu_before.user) + (cpu.system - cpu_before.system)) / max(
        cpu.elapsed - cpu_before.elapsed, 1e-9)
    print(f"CPU: {busy:.0%} of one core (the daemon, the emulator and this bench)"
          + (": CPU-bound, so the run fell behind the devices and its memory holds a backlog;"
             " run again with fewer --trace-frames, or none" if busy > 0.9 else ""))
    if len(maps) >= 2:
        (t0, first), (t1, last) = maps[0], maps[-1]
        grown = sorted(((last.get(k, 0) - first.get(k, 0), k) for k in set(first) | set(last)),
                       reverse=True)
        print(f"mappings that grew most, minute {t0:.1f} -> {t1:.1f} (resident kB):")
        for kb, name in grown[:8]:
            print(f"  {kb:+8d} kB  {name}")
    after = np.array([s for s in samples if s[0] >= warm_s])
    print(f"{args.minutes:g} min, {pipeline.poses} poses; after the {args.warmup_minutes:g} "
          "min warm-up:")
    if len(after) < 3:
        print("  too few samples after the warm-up for a slope")
        return
    minutes = after[:, 0] / 60
    for k, name in ((1, "RSS"), (2, "Python heap")):
        slope = np.polyfit(minutes, after[:, k], 1)[0]
        print(f"  {name}: {after[0, k]:.1f} -> {after[-1, k]:.1f} MB, slope {slope:+.4f} MB/min")
    if len(snapshots) == 2:
        print("  allocation sites that grew most (first sample after the warm-up -> the end):")
        for stat in snapshots[1].compare_to(snapshots[0], "lineno")[:10]:
            print(f"    {stat.size_diff / 1e3:+9.1f} kB  {stat.traceback.format()[-1].strip()}")


if __name__ == "__main__":
    main()
