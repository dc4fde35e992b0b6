"""The emulator's ptys opened with pyserial and read back through the real parsers."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import pytest
import serial

from drivers import PARSERS, AnchorRange, ImuSample, UwbRanges, trek1000
from drivers.emulator import DeviceSpec, Emulator, Faults, Window
from drivers.emulator.scenario import CircleScenario


def read_until_done(emu: Emulator, names: dict[str, str], timeout_s: float = 10.0):
    """Start the emulator and read every port until it finishes, reopening a port that
    vanished. Ports are opened first: pyserial's open() flushes what was already written."""
    ports: dict[str, serial.Serial | None] = {
        n: serial.Serial(emu.ports[n].path, 921600, timeout=0) for n in names}
    emu.start()
    parsers = {n: PARSERS[d]() for n, d in names.items()}
    frames: dict[str, list] = {n: [] for n in names}
    errors = {n: 0 for n in names}
    deadline = time.monotonic() + timeout_s
    drain_until = None
    while time.monotonic() < deadline:
        # after the last write, keep reading briefly: the kernel hands pty bytes to the
        # reader side asynchronously
        if drain_until is None and emu.finished.is_set():
            drain_until = time.monotonic() + 0.2
        done = drain_until is not None and time.monotonic() > drain_until
        for name in names:
            try:
                if ports[name] is None:
                    ports[name] = serial.Serial(emu.ports[name].path, 921600, timeout=0)
                port = ports[name]
                assert port is not None
                frames[name] += parsers[name].feed(port.read(65536), time.time_ns())
            except OSError:  # SerialException and the bare EIO after an unplug
                errors[name] += 1
                if ports[name] is not None:
                    ports[name].close()  # type: ignore[union-attr]
                ports[name] = None
        if done:
            break
        time.sleep(0.005)
    for port in ports.values():
        if port is not None:
            port.close()
    return frames, parsers, errors


def test_clean_link_delivers_every_frame_at_the_device_rate(tmp_path: Path) -> None:
    scenario = CircleScenario(seed=3)
    devices = [DeviceSpec("imu", "wit"), DeviceSpec("uwb", "dwm1001")]
    with Emulator(devices, scenario, duration_s=1.0, link_dir=tmp_path) as emu:
        assert Path(emu.ports["imu"].path).is_symlink()
        frames, parsers, errors = read_until_done(emu, {"imu": "wit", "uwb": "dwm1001"})
    expected_imu = [f for _, f in scenario.imu(1.0)]
    expected_uwb = [f for _, f in scenario.uwb(1.0)]
    # the last IMU cycle leaves on the next wrap, which never comes: flush releases it
    imu = frames["imu"] + parsers["imu"].flush()
    assert len(imu) == len(expected_imu) == 201
    assert all(isinstance(f, ImuSample) for f in imu)
    assert imu[-1].acc_mps2 == pytest.approx(expected_imu[-1].acc_mps2, abs=0.005)
    assert len(frames["uwb"]) == len(expected_uwb) == 11
    assert all(isinstance(f, UwbRanges) and len(f.ranges) == 6 for f in frames["uwb"])
    assert parsers["imu"].stats.bytes_skipped == parsers["uwb"].stats.bytes_skipped == 0
    assert errors == {"imu": 0, "uwb": 0}
    # receive times are increasing and span about the scenario's second
    t = [f.t_ns for f in frames["uwb"]]
    assert t == sorted(t) and 0.8e9 < t[-1] - t[0] < 1.5e9


def test_faulty_link_is_survived_and_counted(tmp_path: Path) -> None:
    faults = Faults(garbage_rate_hz=20, split=True, corrupt_prob=0.05, drop_prob=0.05,
                    stalls=(Window(0.3, 0.2),))
    devices = [DeviceSpec("imu", "wit", faults), DeviceSpec("uwb", "nlink", faults)]
    with Emulator(devices, CircleScenario(seed=5), duration_s=1.5, link_dir=tmp_path) as emu:
        frames, parsers, _ = read_until_done(emu, {"imu": "wit", "uwb": "nlink"})
        counts = emu.counts
    uwb_stats = parsers["uwb"].stats
    # every nlink frame that was sent intact arrives; corrupted ones are caught by checksum
    assert len(frames["uwb"]) == counts["uwb"].frames - counts["uwb"].corrupted
    assert uwb_stats.checksum_errors >= counts["uwb"].corrupted
    assert counts["imu"].garbage_bursts > 0 and parsers["imu"].stats.bytes_skipped > 0
    assert counts["imu"].stalled > 0
    assert len(frames["imu"]) > 0.7 * counts["imu"].frames


def test_unplug_closes_the_port_and_replug_brings_it_back(tmp_path: Path) -> None:
    faults = Faults(unplugs=(Window(0.4, 0.3),))
    devices = [DeviceSpec("uwb", "nlink", faults)]
    with Emulator(devices, CircleScenario(), duration_s=1.5, link_dir=tmp_path) as emu:
        frames, _, errors = read_until_done(emu, {"uwb": "nlink"})
        assert emu.counts["uwb"].unplugs == 1
    assert errors["uwb"] >= 1  # the reader saw the device vanish
    t = [f.t_ns for f in frames["uwb"]]
    gaps = [b - a for a, b in itertools.pairwise(t)]
    assert max(gaps) > 0.25e9  # the unplugged window
    assert (t[-1] - t[0]) > 1.2e9  # and frames again after it


def test_unknown_driver_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown driver"):
        DeviceSpec("imu", "witmotion")


def test_new_devices_are_served_at_their_rate(tmp_path: Path) -> None:
    scenario = CircleScenario(seed=4)
    devices = [DeviceSpec("node2", "nlink-node2"), DeviceSpec("trek", "trek1000")]
    with Emulator(devices, scenario, duration_s=1.0, link_dir=tmp_path) as emu:
        frames, parsers, errors = read_until_done(
            emu, {"node2": "nlink-node2", "trek": "trek1000"})
    expected = [f for _, f in scenario.uwb(1.0)]
    assert errors == {"node2": 0, "trek": 0}
    node2, trek = frames["node2"], frames["trek"]
    assert len(node2) == len(trek) == len(expected) == 11
    # NodeFrame2 carries all six anchors; a TREK1000 network has A0..A3
    assert [r.anchor_id for r in node2[0].ranges] == list(range(6))
    assert all(r.quality == 100.0 for f in node2 for r in f.ranges)  # a direct path
    assert all([r.anchor_id for r in f.ranges] == [0, 1, 2, 3] for f in trek)
    assert trek[-1].ranges[0].range_m == pytest.approx(expected[-1].ranges[0].range_m, abs=1e-3)
    assert parsers["node2"].stats.bytes_skipped == 0
    # the trek stream is mc then mr lines: the mr half is skipped, nothing is malformed
    trek_stats = parsers["trek"].stats
    assert trek_stats.malformed == 0 and trek_stats.bytes_skipped == trek_stats.bytes_in // 2


def test_trek1000_device_answers_the_pc_handshake() -> None:
    """docs/wire-formats.md, sans I/O: replies, the 1 s pause, mr lines off and on."""
    dev = trek1000.Trek1000Device()
    epoch = UwbRanges(0, tuple(AnchorRange(k, 1.0 + k) for k in range(6)))
    assert trek1000.Trek1000Parser().feed(dev.report(0, epoch))[0].ranges == tuple(
        AnchorRange(k, 1.0 + k) for k in range(4))
    assert dev.report(0, epoch).count(b"\r\n") == 2  # mc and mr
    reply = dev.on_input(b"de", 10) + dev.on_input(b"cA$", 10)  # straddling two reads
    assert reply == b"nVer.2.25mx TREK\x00" + bytes((trek1000.S1_CONFIG,)) + b"\r\n"
    assert len(reply) == 20 and reply.startswith(b"nV")  # what the PC app waits for
    assert dev.report(10 + 999_000_000, epoch) == b""  # paused for a second
    assert dev.report(10 + 1_000_000_000, epoch).startswith(b"mc ")
    assert dev.report(10 + 1_000_000_000, epoch).count(b"\r\n") == 1  # decA$: no mr
    assert dev.on_input(b"deca?", 2_000_000_000).startswith(b"nEVB1000 USB2SPI 2.0")
    assert dev.report(2_000_000_000, epoch).count(b"\r\n") == 2  # mr back
    assert dev.on_input(b"deca!", 3_000_000_000)[9:] == b"\r\n"  # n, part id, lot id
    assert dev.on_input(b"hello", 3_000_000_000) == b""


def test_emulated_trek1000_replies_on_the_port(tmp_path: Path) -> None:
    devices = [DeviceSpec("trek", "trek1000")]
    with Emulator(devices, CircleScenario(), duration_s=30, link_dir=tmp_path) as emu:
        with serial.Serial(emu.ports["trek"].path, 115200, timeout=0.05) as port:
            emu.start()
            seen = b""
            deadline = time.monotonic() + 5
            while seen.count(b"mr ") < 2 and time.monotonic() < deadline:
                seen += port.read(4096)
            port.write(b"decA$")
            while b"nV" not in seen and time.monotonic() < deadline:
                seen += port.read(4096)
            after = seen[seen.index(b"nV") :]
            while after.count(b"mc ") < 2 and time.monotonic() < deadline + 3:
                after += port.read(4096)
        assert emu.received["trek"].endswith(b"decA$")
    assert after.startswith(b"nVer.2.25mx TREK\x00")
    # one epoch may have left before the command was read; none with mr after it
    assert after.count(b"mr ") <= 1 and after.count(b"mc ") >= 2
    frames = trek1000.Trek1000Parser().feed(after)
    assert frames and all(len(f.ranges) == 4 for f in frames if isinstance(f, UwbRanges))
