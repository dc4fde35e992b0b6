"""``uwbd demo``: emulated sensors on real pseudo-terminals, read back through the drivers.

This is the pipeline as far as it exists: emulator → pty → pyserial → parser → gating, with
a live line a second and a summary at the end. The fusion core and the daemon (Zenoh, MCAP)
extend it as they land.
"""

from __future__ import annotations

import math
import selectors
import sys
import threading
import time
from pathlib import Path

import serial

from drivers import PARSERS, Parser, UwbRanges
from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from uwbd.fusion.gating import GatingCounters, GatingPolicy, gate
from uwbd.interrupt import wait_until

DEMO_FAULTS = Faults(garbage_rate_hz=0.5, split=True, corrupt_prob=0.01)
READ_BYTES = 4096


def run_demo(workdir: Path, duration_s: float | None, seed: int) -> int:
    """Run until ``duration_s`` or Ctrl-C; prints live lines and a summary. Returns 0."""
    devices = [DeviceSpec("imu", "wit", DEMO_FAULTS), DeviceSpec("uwb", "nlink", DEMO_FAULTS)]
    scenario = CircleScenario(seed=seed)
    with Emulator(devices, scenario, duration_s, workdir) as emu:
        reader = _Reader({d.name: (emu.ports[d.name].path, d.driver) for d in devices})
        print(f"uwbd demo: emulated WitMotion IMU on {emu.ports['imu'].path}, "
              f"Nooploop tag on {emu.ports['uwb'].path}; Ctrl-C to stop", flush=True)
        emu.start()
        try:
            _wait_with(reader, emu, scenario)
        finally:
            reader.close()
        reader.summary(scenario)
    return 0


def _wait_with(reader: _Reader, emu: Emulator, scenario: CircleScenario) -> None:
    stop = threading.Event()
    thread = threading.Thread(target=reader.loop, args=(stop, scenario), daemon=True)
    thread.start()
    try:
        wait_until(emu.finished)
    finally:
        stop.set()
        thread.join(timeout=2)


class _Reader:
    def __init__(self, ports: dict[str, tuple[str, str]]) -> None:
        self.ports = {n: serial.Serial(path, 921600, timeout=0) for n, (path, _) in ports.items()}
        self.parsers: dict[str, Parser] = {n: PARSERS[drv]() for n, (_, drv) in ports.items()}
        self.counts = {n: 0 for n in ports}
        self.gating = GatingCounters()
        self.policy = GatingPolicy()
        self.last_fix: UwbRanges | None = None
        self.errors: list[float] = []
        self.start_ns = time.time_ns()

    def loop(self, stop: threading.Event, scenario: CircleScenario) -> None:
        sel = selectors.DefaultSelector()
        for name, port in self.ports.items():
            sel.register(port.fileno(), selectors.EVENT_READ, name)
        next_print = time.monotonic() + 1.0
        while not stop.is_set():
            for key, _ in sel.select(timeout=0.1):
                self._read(key.data, scenario)
            if time.monotonic() >= next_print:
                next_print += 1.0
                self._line()

    def _read(self, name: str, scenario: CircleScenario) -> None:
        port = self.ports[name]
        try:
            data = port.read(port.in_waiting or 1)
        except OSError:
            return
        t_ns = time.time_ns()
        for frame in self.parsers[name].feed(data, t_ns):
            self.counts[name] += 1
            if isinstance(frame, UwbRanges):
                result = gate(frame, self.policy, self.gating)
                if result.epoch is not None and frame.tag_position_m is not None:
                    self.last_fix = frame
                    truth = scenario.position_m((t_ns - self.start_ns) / 1e9)
                    self.errors.append(math.dist(frame.tag_position_m[:2], truth[:2]))

    def _line(self) -> None:
        elapsed = (time.time_ns() - self.start_ns) / 1e9
        rates = " ".join(f"{n} {c / elapsed:6.1f} Hz" for n, c in self.counts.items())
        pos = "--"
        if self.last_fix is not None and self.last_fix.tag_position_m is not None:
            pos = "({:6.2f}, {:6.2f}, {:5.2f}) m".format(*self.last_fix.tag_position_m)
        skipped = sum(p.stats.bytes_skipped for p in self.parsers.values())
        bad = sum(p.stats.checksum_errors for p in self.parsers.values())
        print(f"{elapsed:6.1f} s  {rates}  tag {pos}  skipped {skipped} B, "
              f"checksum errors {bad}", flush=True)

    def summary(self, scenario: CircleScenario) -> None:
        print("\nsummary:")
        for name, parser in self.parsers.items():
            stats = parser.stats.as_dict()
            last = stats.pop("recent_errors")[-1:]
            print(f"  {name}: {self.counts[name]} frames; parser {stats}"
                  + (f"; last error at {last[0]}" if last else ""))
        print(f"  gating: {self.gating.epochs_passed} epochs passed, "
              f"rejections {dict(self.gating.rejections)}")
        if self.errors:
            rmse = math.sqrt(sum(e * e for e in self.errors) / len(self.errors))
            print(f"  tag's own XY fix vs scenario truth: RMSE {rmse:.3f} m "
                  f"over {len(self.errors)} epochs (fusion arrives with the fusion core)")
        sys.stdout.flush()

    def close(self) -> None:
        for port in self.ports.values():
            port.close()
