"""Several robots behind one Zenoh router, one subscriber on ``uwbd/*/pose``: docs/fleet.md's
fleet walk-through, on loopback (unix sockets), multicast scouting off."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

from emulated import emulated_sources
from procs import UNBUFFERED, UWBD, read_until, uwbd

from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from uwbd.logs.reading import read_log


def robot_config(tmp: Path, name: str, ports: dict[str, str], router: str) -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(f"""
[robot]
name = "{name}"

{emulated_sources(ports)}
[zenoh]
mode = "client"
connect = ["{router}"]
multicast_scouting = false
""")
    return path


def test_two_robots_behind_one_router_one_subscriber(tmp_path: Path) -> None:
    router_at = f"unixsock-stream/{tmp_path / 'router.sock'}"
    procs: list[subprocess.Popen[bytes]] = []
    emulators = []
    try:
        procs.append(subprocess.Popen([*UWBD, "router", "--listen", router_at],
                                      stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                      env=UNBUFFERED))
        read_until(procs[0], b"routing on", 20, "stderr")
        for name, seed in (("r1", 1), ("r2", 2)):
            links = tmp_path / name
            links.mkdir()
            emu = Emulator([DeviceSpec("imu", "wit", Faults()), DeviceSpec("uwb", "nlink")],
                           CircleScenario(seed=seed), duration_s=30.0, link_dir=links)
            emulators.append(emu)
            cfg = robot_config(tmp_path, name, {n: p.path for n, p in emu.ports.items()},
                               router_at)
            daemon = subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir",
                                       str(tmp_path / "logs")], stderr=subprocess.PIPE,
                                      stdout=subprocess.DEVNULL, env=UNBUFFERED)
            procs.append(daemon)
            read_until(daemon, b"uwb: opened", 20, "stderr")
            emu.start()
        # (enough poses that the robot started second has begun: 50 a second from each)
        echo = uwbd("echo", "--prefix", "uwbd/*", "--connect", router_at, "--count", "300",
                    "--timeout", "20")
        assert echo.returncode == 0, echo.stderr
        robots = {line.split("/pose  ")[0] for line in echo.stdout.splitlines()}
        assert robots == {"uwbd/r1", "uwbd/r2"}, echo.stdout[:500]
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=20)
        for emu in emulators:
            emu.close()
    assert [p.returncode for p in procs] == [0, 0, 0]
    # both wrote into one folder, each file named for and stamped with its robot
    logs = sorted((tmp_path / "logs").glob("*.mcap"))
    assert {p.name.split("-")[1] for p in logs} == {"r1", "r2"}
    for path in logs:
        assert read_log(path).metadata["robot"] == path.name.split("-")[1]
