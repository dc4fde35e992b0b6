"""Serial-device emulator: encoded frames written to pseudo-terminals at the devices' timing.

>>> with Emulator([DeviceSpec("imu", "wit"), DeviceSpec("uwb", "nlink")]) as emu:  # doctest: +SKIP
...     emu.start()
...     serial.Serial(emu.ports["imu"].path)  # read it like the real device

One thread paces all devices from a single start instant (no drift builds up), applies each
device's :class:`Faults`, and drains whatever the reader writes to the device. A device with
a model in :data:`DEVICES` (TREK1000) also answers it: the model turns each epoch into the
device's bytes and replies to the host's commands (the reply is written after the next
event of any device, so within one sample period of the fastest one; a command that changes
what the device reports takes effect from its next epoch but one).
"""

from __future__ import annotations

import heapq
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from drivers import dwm1001, dwm1001_tlv, nlink, nlink_node2, trek1000, wit
from drivers.emulator.faults import REPLUG, UNPLUG, Event, FaultCounts, Faults, Window, inject
from drivers.emulator.pty import EmulatedPort
from drivers.emulator.scenario import CircleScenario

ENCODERS: dict[str, Callable[[Any], bytes]] = {
    "wit": wit.encode,
    "dwm1001": dwm1001.encode,
    "dwm1001-tlv": dwm1001_tlv.encode,
    "nlink": nlink.encode,
    "nlink-node2": nlink_node2.encode,
    # a TREK1000 tag: mc then mr lines, ranges to A0..A3 (the others are not heard)
    "trek1000": trek1000.encode_tag_report,
    "trek1000-raw": trek1000.encode_tag_report,
}
IMU_DRIVERS = frozenset({"wit"})
MAX_RECEIVED_BYTES = 65536  # what the reader sent to a device, kept for inspection
DEFAULT_BAUD = {"wit": 921600, "dwm1001": 115200, "dwm1001-tlv": 115200, "nlink": 921600,
                "nlink-node2": 921600, "trek1000": 115200, "trek1000-raw": 115200}


class DeviceModel(Protocol):
    """A device that keeps state: its bytes for each epoch (``b""``: it sends nothing), and
    its replies to what the host sends. ``t_ns``: the emulator's clock, ns from its start."""

    def report(self, t_ns: int, frame: Any) -> bytes: ...

    def on_input(self, data: bytes, t_ns: int) -> bytes: ...


class Encoder:
    """The model of a device that only sends: its encoder, deaf to the host."""

    def __init__(self, encode: Callable[[Any], bytes]) -> None:
        self.encode = encode

    def report(self, t_ns: int, frame: Any) -> bytes:
        return self.encode(frame)

    def on_input(self, data: bytes, t_ns: int) -> bytes:
        return b""


DEVICES: dict[str, Callable[[], DeviceModel]] = {
    "trek1000": trek1000.Trek1000Device,
    "trek1000-raw": trek1000.Trek1000Device,
}


def device_model(driver: str) -> DeviceModel:
    """A fresh model of a device speaking ``driver``."""
    make = DEVICES.get(driver)
    return make() if make is not None else Encoder(ENCODERS[driver])


@dataclass(frozen=True)
class DeviceSpec:
    """One emulated device: its port name, wire format, faults and (nominal) baud rate."""

    name: str
    driver: str
    faults: Faults = field(default_factory=Faults)
    baud: int | None = None

    def __post_init__(self) -> None:
        if self.driver not in ENCODERS:
            raise ValueError(f"unknown driver {self.driver!r}; known: {', '.join(ENCODERS)}")


class Emulator:
    """Runs devices of a scenario on ptys until ``duration_s`` (None: until stopped)."""

    def __init__(
        self, devices: list[DeviceSpec], scenario: CircleScenario | None = None,
        duration_s: float | None = None, link_dir: Path | None = None,
    ) -> None:
        self.devices = devices
        self.scenario = scenario or CircleScenario()
        self.duration_s = duration_s
        self.ports = {d.name: EmulatedPort(link_dir / d.name if link_dir else None)
                      for d in devices}
        self.counts = {d.name: FaultCounts() for d in devices}
        self.received: dict[str, bytearray] = {d.name: bytearray() for d in devices}
        self.models = {d.name: device_model(d.driver) for d in devices}
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _events(self, index: int, dev: DeviceSpec) -> Iterator[tuple[int, int, bytes | None]]:
        model = self.models[dev.name]
        frames: Iterator[tuple[int, Any]] = (
            self.scenario.imu(self.duration_s) if dev.driver in IMU_DRIVERS
            else self.scenario.uwb(self.duration_s))
        # b"" is REPLUG among events: an epoch a device does not report is left out
        encoded = ((t, data) for t, frame in frames if (data := model.report(t, frame)))
        baud = dev.baud or DEFAULT_BAUD[dev.driver]
        events: Iterator[Event] = inject(
            encoded, dev.faults, baud, self.scenario.seed * 1000 + index, self.counts[dev.name])
        for t_ns, payload in events:
            yield t_ns, index, payload

    def start(self) -> None:
        """Start writing in a background thread."""
        self._thread = threading.Thread(target=self.run, name="uwbd-emulator", daemon=True)
        self._thread.start()

    def run(self) -> None:
        """Write all events at their times; returns at the end of the scenario or on stop."""
        streams = [self._events(i, d) for i, d in enumerate(self.devices)]
        ports = [self.ports[d.name] for d in self.devices]
        start_ns = time.monotonic_ns()
        try:
            for t_ns, index, payload in heapq.merge(*streams, key=lambda e: e[0]):
                delay_ns = start_ns + t_ns - time.monotonic_ns()
                if delay_ns > 0 and self._stop.wait(delay_ns / 1e9):
                    break
                if self._stop.is_set():
                    break
                port = ports[index]
                if payload is UNPLUG:
                    port.unplug()
                elif payload == REPLUG:
                    port.plug()
                else:
                    port.write(payload)
                self._answer(ports, t_ns)
        finally:
            self.finished.set()

    def _answer(self, ports: list[EmulatedPort], t_ns: int) -> None:
        """Drain what the reader sent to each device; write the device's replies."""
        for dev, port in zip(self.devices, ports, strict=True):
            data = port.read_input()
            if not data:
                continue
            received = self.received[dev.name]
            received += data
            del received[:-MAX_RECEIVED_BYTES]
            reply = self.models[dev.name].on_input(data, t_ns)
            if reply:
                port.write(reply)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def close(self) -> None:
        self.stop()
        for port in self.ports.values():
            port.close()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


__all__ = ["DEFAULT_BAUD", "DEVICES", "ENCODERS", "DeviceModel", "DeviceSpec", "Emulator",
           "FaultCounts", "Faults", "Window", "device_model"]
