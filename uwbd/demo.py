"""``uwbd demo``: emulated sensors on real pseudo-terminals, fused into live poses.

The pipeline as far as it exists: emulator → pty → pyserial → parsers → a small time-ordered
release (frames wait ``ALIGN_WAIT_NS`` so that both ports' frames reach the filter in
timestamp order) → the tight error-state filter, with a live line a second and, at the end,
a summary with the accuracy against the scenario's truth. The daemon (Zenoh, MCAP, the real
aligner) replaces the reading loop as it lands.
"""

from __future__ import annotations

import heapq
import itertools
import math
import selectors
import sys
import threading
import time
from pathlib import Path

import serial

from drivers import PARSERS, Frame, ImuSample, Parser, UwbRanges
from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from uwbd.fusion.filter import Filter, FilterConfig
from uwbd.fusion.types import Pose
from uwbd.interrupt import shielded, wait_until

DEMO_FAULTS = Faults(garbage_rate_hz=0.5, split=True, corrupt_prob=0.01)
ALIGN_WAIT_NS = 20_000_000  # a frame is held this long for later-read, earlier-stamped ones


def run_demo(workdir: Path, duration_s: float | None, seed: int) -> int:
    """Run until ``duration_s`` or Ctrl-C; prints live lines and a summary. Returns 0."""
    devices = [DeviceSpec("imu", "wit", DEMO_FAULTS), DeviceSpec("uwb", "nlink", DEMO_FAULTS)]
    scenario = CircleScenario(seed=seed)
    emu = Emulator(devices, scenario, duration_s, workdir)
    stop = threading.Event()
    reader: _Reader | None = None
    thread: threading.Thread | None = None
    try:
        reader = _Reader({d.name: (emu.ports[d.name].path, d.driver) for d in devices},
                         scenario)
        print(f"uwbd demo: emulated WitMotion IMU on {emu.ports['imu'].path}, "
              f"Nooploop tag on {emu.ports['uwb'].path}; Ctrl-C to stop", flush=True)
        thread = threading.Thread(target=reader.loop, args=(stop,), daemon=True)
        thread.start()
        emu.start()
        wait_until(emu.finished)
    finally:
        with shielded():
            stop.set()
            if thread is not None:
                thread.join(timeout=2)
            emu.close()
            if reader is not None:
                reader.close()
                reader.summary()
    return 0


class _Reader:
    def __init__(self, ports: dict[str, tuple[str, str]], scenario: CircleScenario) -> None:
        self.ports = {n: serial.Serial(path, 921600, timeout=0) for n, (path, _) in ports.items()}
        self.parsers: dict[str, Parser] = {n: PARSERS[drv]() for n, (_, drv) in ports.items()}
        self.counts = dict.fromkeys(ports, 0)
        self.scenario = scenario
        self.filter = Filter(FilterConfig(anchors_m=dict(enumerate(scenario.anchors_m))))
        self.pending: list[tuple[int, int, Frame]] = []
        self._order = itertools.count()
        self.pose: Pose | None = None
        self.fused_err_m: list[float] = []
        self.tag_err_m: list[float] = []
        self.start_ns = time.time_ns()

    def loop(self, stop: threading.Event) -> None:
        sel = selectors.DefaultSelector()
        for name, port in self.ports.items():
            sel.register(port.fileno(), selectors.EVENT_READ, name)
        next_print = time.monotonic() + 1.0
        while not stop.is_set():
            for key, _ in sel.select(timeout=0.005):
                self._read(key.data)
            self._release(time.time_ns() - ALIGN_WAIT_NS)
            if time.monotonic() >= next_print:
                next_print += 1.0
                self._line()

    def _read(self, name: str) -> None:
        port = self.ports[name]
        try:
            data = port.read(port.in_waiting or 1)
        except OSError:
            return
        for frame in self.parsers[name].feed(data, time.time_ns()):
            self.counts[name] += 1
            heapq.heappush(self.pending, (frame.t_ns, next(self._order), frame))

    def _release(self, until_ns: int) -> None:
        """Frames up to ``until_ns`` to the filter, in timestamp order."""
        while self.pending and self.pending[0][0] <= until_ns:
            _, _, frame = heapq.heappop(self.pending)
            if isinstance(frame, ImuSample):
                self.filter.predict(frame)
                continue
            self.filter.update(frame)
            truth = self.scenario.position_m((frame.t_ns - self.start_ns) / 1e9)
            if isinstance(frame, UwbRanges) and frame.tag_position_m is not None:
                self.tag_err_m.append(math.dist(frame.tag_position_m[:2], truth[:2]))
            pose = self.filter.pose()
            if pose is not None:
                self.pose = pose
                self.fused_err_m.append(math.dist(pose.position_m[:2], truth[:2]))

    def _line(self) -> None:
        elapsed = (time.time_ns() - self.start_ns) / 1e9
        rates = " ".join(f"{n} {c / elapsed:5.1f} Hz" for n, c in self.counts.items())
        if self.pose is None:
            state = self.filter.status
        else:
            x, y, z = self.pose.position_m
            sx, sy = math.sqrt(self.pose.covariance[0]), math.sqrt(self.pose.covariance[7])
            speed = math.hypot(*self.pose.velocity_mps[:2])
            heading = "heading ok" if self.pose.heading_observable else "heading unknown"
            state = (f"pose ({x:6.2f}, {y:6.2f}, {z:5.2f}) m ±({sx:.2f}, {sy:.2f}) "
                     f"{speed:4.2f} m/s {heading}")
        skipped = sum(p.stats.bytes_skipped for p in self.parsers.values())
        print(f"{elapsed:6.1f} s  {rates}  {state}  skipped {skipped} B", flush=True)

    def summary(self) -> None:
        self._release(2**63 - 1)
        print("\nsummary:")
        for name, parser in self.parsers.items():
            stats = parser.stats.as_dict()
            last = stats.pop("recent_errors")[-1:]
            print(f"  {name}: {self.counts[name]} frames; parser {stats}"
                  + (f"; last error at {last[0]}" if last else ""))
        print(f"  filter: {self.filter.status}; {dict(self.filter.counters)}; "
              f"range rejections {dict(self.filter.gating.rejections)}")
        for label, errs in (("fused pose", self.fused_err_m), ("tag's own fix", self.tag_err_m)):
            if errs:
                rmse = math.sqrt(sum(e * e for e in errs) / len(errs))
                print(f"  {label} vs scenario truth: XY RMSE {rmse:.3f} m over {len(errs)} epochs")
        sys.stdout.flush()

    def close(self) -> None:
        for port in self.ports.values():
            port.close()
