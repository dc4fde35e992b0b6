"""The daemon as users run it: emulator ptys → `uwbd run` subprocess → MCAP, then replay."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from emulated import emulated_sources
from procs import UNBUFFERED, read_until

from drivers.emulator import DeviceSpec, Emulator, Faults, Window
from drivers.emulator.scenario import CircleScenario
from uwbd.config import parse
from uwbd.fusion.core import native
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.service.narrator import Narrator
from uwbd.service.pipeline import Pipeline, PoseList
from uwbd.service.ports import ReadQueue
from uwbd.service.replay import replay
from uwbd.tools.logtools import write_simulation
from uwbd.tools.simulator import SimConfig, simulate

UWBD = [sys.executable, "-m", "uwbd"]


def write_config(tmp: Path, ports: dict[str, str]) -> Path:
    text = f"""
{emulated_sources(ports)}
[zenoh]
prefix = "uwbd/test"
listen = ["unixsock-stream/{tmp / 'z.sock'}"]
multicast_scouting = false  # tests never send beyond loopback
"""
    path = tmp / "cfg.toml"
    path.write_text(text)
    return path


def start_daemon(cfg: Path, logs: Path, *extra: str,
                 env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    return subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir", str(logs), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=None if env is None else {**os.environ, **env})


def poses_of(path: Path) -> list[tuple[int, tuple[float, ...]]]:
    contents = read_log(path)
    return [(d["t_ns"], (*d["pose"]["position"].values(), *d["pose"]["orientation"].values()))
            for d in contents.json("/pose")]


@pytest.fixture
def emulator(tmp_path: Path):
    devices = [DeviceSpec("imu", "wit", Faults(garbage_rate_hz=2, split=True)),
               DeviceSpec("uwb", "nlink", Faults(split=True, unplugs=(Window(2.5, 0.7),)))]
    with Emulator(devices, CircleScenario(seed=2), duration_s=6.0, link_dir=tmp_path) as emu:
        yield emu


@pytest.mark.parametrize("reads", ["reader thread", "event loop"])
def test_live_run_logs_everything_and_replays_bit_for_bit(tmp_path: Path, emulator,
                                                          reads: str) -> None:
    """With the C reader's thread (and C core), and without either (UWBD_PURE_PYTHON=1:
    the event loop reads the ports, the filter is Python's): the same behaviour."""
    if reads == "reader thread" and native.core is None:
        pytest.skip(native.implementation)
    pure = reads == "event loop"
    cfg = write_config(tmp_path, {n: p.path for n, p in emulator.ports.items()})
    daemon = start_daemon(cfg, tmp_path / "logs",
                          env={native.PURE_PYTHON_ENV: "1" if pure else "0"})
    time.sleep(0.8)  # the daemon opens the ports; bytes sent before that are flushed by open()
    emulator.start()
    emulator.finished.wait(15)
    time.sleep(0.3)
    daemon.send_signal(signal.SIGTERM)
    _, err = daemon.communicate(timeout=20)
    assert daemon.returncode == 0, err.decode()
    assert f"serial reads: {reads})" in err.decode()
    (log,) = sorted((tmp_path / "logs").glob("*.mcap"))
    contents = read_log(log)
    assert not contents.truncated  # finished cleanly on SIGTERM
    assert {"/raw/imu", "/raw/uwb", "/imu", "/uwb", "/pose", "/status"} <= contents.topics()
    assert "[[sources]]" in contents.metadata["config_toml"]
    live = poses_of(log)
    assert len(live) > 100
    # the UWB port was unplugged for 0.7 s and came back: the daemon saw it and went on
    status = list(contents.json("/status"))[-1]
    uwb = status["sources"]["uwb"]
    assert uwb["losses"] >= 1 and uwb["opens"] >= 2, uwb
    assert status["parsers"]["imu"]["bytes_skipped"] > 0  # the garbage was there, and survived
    t_last_uwb = max(m.log_time_ns for m in contents.messages if m.topic == "/raw/uwb")
    t_first = min(m.log_time_ns for m in contents.messages)
    assert (t_last_uwb - t_first) / 1e9 > 4.5  # ranges again after the replug
    # replay: the same reads through the same pipeline give the same poses, bit for bit
    out = tmp_path / "replayed.mcap"
    with native.pure_python() if pure else contextlib.nullcontext():
        pipeline, _ = replay(contents, str(log), out)
    assert poses_of(out) == live
    assert pipeline.poses == len(live)


def test_kill_9_loses_at_most_about_a_second(tmp_path: Path, emulator) -> None:
    cfg = write_config(tmp_path, {n: p.path for n, p in emulator.ports.items()})
    daemon = start_daemon(cfg, tmp_path / "logs")
    time.sleep(0.8)
    emulator.start()
    time.sleep(4.0)
    killed_ns = time.time_ns()
    daemon.send_signal(signal.SIGKILL)
    daemon.communicate(timeout=10)
    (log,) = sorted((tmp_path / "logs").glob("*.mcap"))
    contents = read_log(log)
    assert contents.truncated  # no footer: cut short
    last_ns = max(m.log_time_ns for m in contents.messages)
    assert (killed_ns - last_ns) / 1e9 < 1.6
    assert len(list(contents.json("/pose"))) > 50


def test_absent_port_is_retried_and_shown(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"imu": str(tmp_path / "nope-imu"),
                                  "uwb": str(tmp_path / "nope-uwb")})
    result = subprocess.run([*UWBD, "run", "-c", str(cfg), "--log-dir", str(tmp_path / "l"),
                             "--duration", "1.5"], capture_output=True, text=True, timeout=30,
                            check=False)
    # nothing could be opened: said per port as it is retried, and the run fails
    assert result.returncode == 1, result.stderr
    assert f"imu: cannot open {tmp_path / 'nope-imu'}: No such file" in result.stderr
    assert "stopped after" in result.stderr and "0 poses" in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("uwbd run: no port could be opened")


@pytest.mark.parametrize(("text", "message"), [
    ("[fusion]\nmode = 3\n", "cfg.toml: fusion.mode: expected a string, got 3 (an integer)"),
    ("[[sources]]\nname = 'imu'\ndriver = 'wit'\n", "cfg.toml: sources[0].port: required"),
    ("[pipeline]\npose_rate_hz = -5\n", "cfg.toml: pipeline.pose_rate_hz: must be at least 0.1"),
    ("[zenoh\n", "cfg.toml"),
])
def test_malformed_config_is_one_clear_line_and_exit_2(tmp_path: Path, text: str,
                                                      message: str) -> None:
    (tmp_path / "cfg.toml").write_text(text)
    result = subprocess.run([*UWBD, "run", "-c", "cfg.toml"], cwd=tmp_path, capture_output=True,
                            text=True, timeout=30, check=False)
    assert result.returncode == 2
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_replay_of_a_simulated_log_is_deterministic(tmp_path: Path) -> None:
    subprocess.run([*UWBD, "simulate", "-o", "s.mcap", "--duration", "25", "--seed", "3"],
                   cwd=tmp_path, check=True, capture_output=True, timeout=60)
    outs = []
    for name in ("a.mcap", "b.mcap"):
        r = subprocess.run([*UWBD, "replay", "s.mcap", "-o", name], cwd=tmp_path,
                           capture_output=True, text=True, timeout=120, check=False)
        assert r.returncode == 0, r.stderr
        outs.append(poses_of(tmp_path / name))
    assert outs[0] == outs[1] and len(outs[0]) > 1000
    # and the replayed output is itself a log that replays to the same poses
    again = replay(read_log(tmp_path / "a.mcap"), "a.mcap")[1].poses
    assert [(p.t_ns, (*p.position_m, *p.orientation_xyzw)) for p in again] == outs[0]


def test_poses_status_and_liveliness_over_zenoh(tmp_path: Path, emulator) -> None:
    """A Zenoh subscriber in the test and `uwbd echo` both see the daemon."""
    sock = tmp_path / "z.sock"
    cfg = write_config(tmp_path, {n: p.path for n, p in emulator.ports.items()})
    daemon = start_daemon(cfg, tmp_path / "logs")
    session = None
    try:
        for _ in range(100):
            if sock.exists():
                break
            time.sleep(0.05)
        zcfg = zenoh.Config.from_json5(json.dumps({
            "mode": "peer", "connect": {"endpoints": [f"unixsock-stream/{sock}"]},
            "scouting": {"multicast": {"enabled": False}}}))
        session = zenoh.open(zcfg)
        poses: list[dict[str, object]] = []
        sub = session.declare_subscriber("uwbd/test/pose",
                                         lambda s: poses.append(json.loads(s.payload.to_bytes())))
        time.sleep(0.5)
        emulator.start()
        deadline = time.monotonic() + 5.0  # the emulator sends for 6 s; a loaded machine is slow
        while len(poses) <= 50 and time.monotonic() < deadline:
            time.sleep(0.1)
        alive = [str(r.ok.key_expr) for r in session.liveliness().get("uwbd/**", timeout=2.0)
                 if r.ok is not None]
        status = [json.loads(r.ok.payload.to_bytes())
                  for r in session.get("uwbd/test/status", timeout=2.0) if r.ok is not None]
        echo = subprocess.run([*UWBD, "echo", "--prefix", "uwbd/test", "--connect",
                               f"unixsock-stream/{sock}", "--count", "3", "--timeout", "10"],
                              capture_output=True, text=True, timeout=30, check=False)
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        daemon.send_signal(signal.SIGTERM)
        daemon.communicate(timeout=20)
    assert daemon.returncode == 0
    assert alive == ["uwbd/test/alive"]
    assert len(poses) > 50
    assert poses[-1]["frame_id"] == "enu" and set(poses[-1]["pose"]) == {"position", "orientation"}
    assert status and status[0]["sources"]["imu"]["state"] == "open"
    assert echo.returncode == 0, echo.stderr
    assert len([x for x in echo.stdout.splitlines() if " p=(" in x]) == 3


def test_systemd_notifications(tmp_path: Path) -> None:
    """READY, WATCHDOG at half WATCHDOG_USEC, STATUS, and STOPPING on SIGTERM."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(str(tmp_path / "notify.sock"))
    listener.settimeout(0.2)
    cfg = write_config(tmp_path, {"imu": str(tmp_path / "absent-imu"),
                                  "uwb": str(tmp_path / "absent-uwb")})
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"),
           "WATCHDOG_USEC": "400000"}
    daemon = subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir", str(tmp_path / "l")],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    messages: list[str] = []
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and sum("WATCHDOG=1" in m for m in messages) < 4:
            with contextlib.suppress(TimeoutError):
                messages.append(listener.recv(4096).decode())
        daemon.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any("STOPPING=1" in m for m in messages):
            with contextlib.suppress(TimeoutError):
                messages.append(listener.recv(4096).decode())
    finally:
        daemon.communicate(timeout=20)
        listener.close()
    assert messages[0].startswith("READY=1\nSTATUS=imu closed, uwb closed")
    assert sum(m == "WATCHDOG=1" for m in messages) >= 4
    assert any(m.startswith("STOPPING=1") for m in messages)
    assert daemon.returncode == 1  # its ports were never there: a failed run


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[1] / "config").glob("*.toml")),
                         ids=lambda p: p.name)
def test_shipped_configs_are_valid(path: Path) -> None:
    result = subprocess.run([*UWBD, "check-config", str(path)], capture_output=True, text=True,
                            timeout=30, check=False)
    assert result.returncode == 0, result.stderr
    assert ": ok (" in result.stdout


def test_unwritable_log_directory_stops_the_log_not_the_fusion(tmp_path: Path) -> None:
    """The log directory cannot be created (its parent is a file): poses keep flowing and
    the status says why nothing is logged."""
    sim_log = tmp_path / "s.mcap"
    subprocess.run([*UWBD, "simulate", "-o", str(sim_log), "--duration", "25", "--seed", "4"],
                   check=True, capture_output=True, timeout=60)
    contents = read_log(sim_log)
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    config = parse(contents.metadata["config_toml"])
    sink = McapSink(config, directory=blocker / "logs")
    poses = PoseList()
    pipeline = Pipeline(config, [sink, poses])
    for m in contents.messages:
        if m.topic.startswith("/raw/"):
            pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
    pipeline.finish()
    pipeline.close()
    assert len(poses.poses) > 1000
    said = f"logging stopped: cannot write log {blocker / 'logs'}/"
    assert sink.error.startswith(said)
    # (the status names the last try before it; the log, written behind, tried once more
    # as it closed)
    [error] = poses.statuses[-1]["sink_errors"]
    assert error.startswith(said) and error.endswith("Not a directory")


def test_imported_log_replays_from_its_decoded_channels(tmp_path: Path) -> None:
    data = Path(__file__).resolve().parents[2] / "shared" / "data" / "iasl-s1"
    if not data.is_dir():
        pytest.skip("shared/data not beside the repository")
    subprocess.run([*UWBD, "import", "iasl", str(data), "-o", "f.mcap"], cwd=tmp_path,
                   check=True, capture_output=True, timeout=60)
    result = subprocess.run([*UWBD, "replay", "f.mcap", "-o", "r.mcap"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert len(poses_of(tmp_path / "r.mcap")) > 4000


def test_dwm1001_tlv_source_polls_loc_get(tmp_path: Path) -> None:
    """A DWM1001 in TLV mode answers requests only: the source asks at 10 Hz."""
    devices = [DeviceSpec("uwb", "dwm1001-tlv")]
    with Emulator(devices, CircleScenario(seed=2), duration_s=3.0, link_dir=tmp_path) as emu:
        ports = {"imu": str(tmp_path / "no-imu"), "uwb": emu.ports["uwb"].path}
        cfg = write_config(tmp_path, ports)
        cfg.write_text(cfg.read_text().replace('driver = "nlink"', 'driver = "dwm1001-tlv"'))
        daemon = start_daemon(cfg, tmp_path / "logs")
        time.sleep(0.8)
        emu.start()
        emu.finished.wait(10)
        daemon.send_signal(signal.SIGTERM)
        daemon.communicate(timeout=20)
        requests = bytes(emu.received["uwb"])
    assert daemon.returncode == 0
    assert requests.count(b"\x0c\x00") >= 20  # ~10 Hz for the ~3 s the port was open
    (log,) = sorted((tmp_path / "logs").glob("*.mcap"))
    uwb = list(read_log(log).json("/uwb"))
    assert len(uwb) > 20 and len(uwb[0]["ranges"]) == 6


def test_samples_of_one_read_get_their_own_times(tmp_path: Path) -> None:
    """Two IMU cycles in one read (the port was read late) must both reach the filter."""
    sim_log = tmp_path / "s.mcap"
    subprocess.run([*UWBD, "simulate", "-o", str(sim_log), "--duration", "25", "--seed", "6"],
                   check=True, capture_output=True, timeout=60)
    contents = read_log(sim_log)
    config = parse(contents.metadata["config_toml"])
    raw = [m for m in contents.messages if m.topic.startswith("/raw/")]
    poses = PoseList()
    pipeline = Pipeline(config, [poses])
    merged = 0
    k = 0
    while k < len(raw):  # every 10th pair of IMU reads arrives as one read
        m = raw[k]
        nxt = raw[k + 1] if k + 1 < len(raw) else None
        if m.topic == "/raw/imu" and nxt is not None and nxt.topic == "/raw/imu" and k % 10 == 0:
            pipeline.on_bytes("imu", nxt.log_time_ns, m.data + nxt.data)
            merged += 1
            k += 2
            continue
        pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
        k += 1
    pipeline.finish()
    assert merged > 100
    assert pipeline.filter.counters["imu_out_of_order"] == 0
    assert len(poses.poses) > 1000


def test_read_queue_holds_imu_reads_until_a_pose_is_due_and_changes_nothing(
        tmp_path: Path) -> None:
    sim = simulate(SimConfig(segments=((2.0, 0.0, 0.0, 0.0), (2.0, 1.0, 0.3, 0.0)), seed=4))
    write_simulation(sim, tmp_path / "sim.mcap")
    contents = read_log(tmp_path / "sim.mcap")
    config = parse(contents.metadata["config_toml"], "sim")
    reads = [(m.topic.removeprefix("/raw/"), m.log_time_ns, m.data)
             for m in contents.messages if m.topic.startswith("/raw/")]
    direct = PoseList()
    pipeline = Pipeline(config, [direct])
    for read in reads:
        pipeline.on_bytes(*read)
    pipeline.finish()

    queued = PoseList()
    log = McapSink(config, path=tmp_path / "queued.mcap", paced=True)
    pipeline = Pipeline(config, [queued, log])
    queue = ReadQueue(pipeline, idle=log.write_pending)
    held = 0
    for source, t_ns, data in reads:
        before = pipeline.parsers[source].stats.bytes_in
        queue.push(source, t_ns, data)
        processed = pipeline.parsers[source].stats.bytes_in > before
        if source == "uwb" or t_ns >= pipeline.next_pose_due_ns:
            assert processed
        held += not processed
    queue.flush()
    pipeline.finish()
    pipeline.close()
    # IMU reads that bring no pose waited for the next one (the log's are batched as the
    # daemon reads: a few samples each, so most bring one) ...
    assert held > len([r for r in reads if r[0] == "imu"]) / 10
    assert queued.poses == direct.poses  # ... and the poses are the same, bit for bit
    # the log, written behind, still holds every read in order
    logged = [(m.topic.removeprefix("/raw/"), m.log_time_ns, m.data)
              for m in read_log(tmp_path / "queued.mcap").messages if m.topic.startswith("/raw/")]
    assert logged == reads


def test_the_narrator_says_each_anchor_finding_once_until_it_goes(
        caplog: pytest.LogCaptureFixture) -> None:
    """One warning line a finding: not again while it stands, again once it went and came
    back."""
    narrator = Narrator()
    finding = {"anchor": 3, "bias_m": -0.3, "sigma_m": 0.04,
               "finding": "anchor 3: its ranges are ~0.30 m short against the other anchors'"}
    with caplog.at_level("WARNING", logger="uwbd"):
        for k, findings in enumerate(([], [finding], [finding], [], [finding])):
            narrator.status(k * 1_000_000_000, {"health": {"phase": "tracking"},
                                     "anchor_findings": findings})
    said = [r.getMessage() for r in caplog.records if "anchor 3" in r.getMessage()]
    assert said == [finding["finding"]] * 2


def test_silent_ports_are_stalled_unhealthy_and_said_until_bytes_come_back(
        tmp_path: Path) -> None:
    """Both devices send nothing for 3 s (powered but hung): the status says each port is
    stalled and the estimate unhealthy within about a second, a line says it, and another
    when the bytes are back."""
    devices = [DeviceSpec("imu", "wit", Faults(stalls=(Window(3.0, 3.0),))),
               DeviceSpec("uwb", "nlink", Faults(stalls=(Window(3.0, 3.0),)))]
    sock = tmp_path / "z.sock"
    statuses: list[tuple[float, dict[str, object]]] = []
    with Emulator(devices, CircleScenario(seed=2), duration_s=9.0, link_dir=tmp_path) as emu:
        cfg = write_config(tmp_path, {n: p.path for n, p in emu.ports.items()})
        daemon = start_daemon(cfg, tmp_path / "logs")
        session = None
        try:
            for _ in range(100):
                if sock.exists():
                    break
                time.sleep(0.05)
            session = zenoh.open(zenoh.Config.from_json5(json.dumps({
                "mode": "client", "connect": {"endpoints": [f"unixsock-stream/{sock}"]},
                "scouting": {"multicast": {"enabled": False}}})))
            session.declare_subscriber("uwbd/test/status", lambda s: statuses.append(
                (time.monotonic(), json.loads(s.payload.to_bytes()))))
            time.sleep(0.3)
            started = time.monotonic()
            emu.start()
            while time.monotonic() - started < 8.5:
                time.sleep(0.1)
        finally:
            if session is not None:
                session.close()
            daemon.send_signal(signal.SIGTERM)
            _, err = daemon.communicate(timeout=20)
    assert daemon.returncode == 0, err
    log = err.decode()

    def when(cond: object) -> list[float]:
        return [t - started for t, s in statuses if cond(s)]  # type: ignore[operator]

    stalled = when(lambda s: {v["state"] for v in s["sources"].values()} == {"stalled"})
    assert stalled, [s["sources"] for _, s in statuses]
    # the stall begins 3.0 s in: both said within 1 s (stall_after_s) + a status period + slack
    assert 3.5 < stalled[0] < 5.6, stalled
    assert not any(s["health"]["healthy"] for t, s in statuses if t - started in stalled)
    back = [t for t in when(lambda s: {v["state"] for v in s["sources"].values()} == {"open"})
            if t > stalled[-1]]
    assert back, "the ports were never open again after the stall"
    last = statuses[-1][1]["sources"]
    assert all(v["stalls"] == 1 for v in last.values()), last
    for name in ("imu", "uwb"):
        assert f"{name}: no byte from" in log and "stalled (is the device powered" in log
        assert f"{name}: bytes again from" in log


def test_a_lost_router_is_in_the_status_and_said_when_it_goes_and_comes_back(
        tmp_path: Path, emulator) -> None:
    router_at = f"unixsock-stream/{tmp_path / 'router.sock'}"

    def router() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen([*UWBD, "router", "--listen", router_at],
                                stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                env=UNBUFFERED)
        read_until(proc, b"routing on", 20, "stderr")
        return proc

    cfg = write_config(tmp_path, {n: p.path for n, p in emulator.ports.items()})
    cfg.write_text(cfg.read_text().replace(
        f'listen = ["unixsock-stream/{tmp_path / "z.sock"}"]',
        f'mode = "client"\nconnect = ["{router_at}"]\nlisten = []'))
    first = router()
    daemon = start_daemon(cfg, tmp_path / "logs")
    second = None
    try:
        read_until(daemon, b"uwb: opened", 20, "stderr")
        emulator.start()
        time.sleep(1.5)
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=20)
        time.sleep(2.0)
        second = router()
        # Zenoh's client retries on its own schedule (seconds): wait for it, then a status
        said = read_until(daemon, b"zenoh: connected again", 30, "stderr")
        time.sleep(1.5)
    finally:
        daemon.send_signal(signal.SIGTERM)
        _, err = daemon.communicate(timeout=20)
        if second is not None:
            second.send_signal(signal.SIGINT)
            second.communicate(timeout=20)
    assert daemon.returncode == 0, err
    log = (said + err).decode()
    assert "zenoh: no router or peer reached" in log and "zenoh: connected again" in log, log
    (path,) = (tmp_path / "logs").glob("*.mcap")
    states = [s["zenoh"]["state"] for s in read_log(path).json("/status") if "zenoh" in s]
    assert "disconnected" in states and states[-1] == "up", states
    assert states.index("up") < states.index("disconnected")
