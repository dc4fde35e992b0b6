"""``uwbd demo``: the real daemon against emulated sensors, with live poses in the terminal.

The emulator serves a WitMotion IMU and a Nooploop tag on pseudo-terminals (with a little
line noise); the daemon (:func:`uwbd.service.daemon.run`: serial sources → drivers → aligner →
fusion → MCAP + Zenoh) reads them like real ports. A view prints a pose line a second;
Ctrl-C stops everything cleanly and prints a summary with the accuracy against the
scenario's truth and where the log is. Zenoh listens on a unix socket in the work
directory (no network traffic), which ``uwbd echo`` can connect to.
"""

from __future__ import annotations

import asyncio
import math
import os
import shlex
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from drivers.frames import Frame
from uwbd.config import Config, SourceConfig, parse, to_toml
from uwbd.fusion.types import Pose
from uwbd.logs.mcaplog import pose_message
from uwbd.logs.sink import McapSink
from uwbd.service.daemon import run
from uwbd.service.interrupt import quiet_stdout, shielded
from uwbd.service.pipeline import Sink

DEMO_FAULTS = Faults(garbage_rate_hz=0.5, split=True, corrupt_prob=0.01)
PREFIX = "uwbd/demo"


@runtime_checkable
class JsonOutput(Protocol):
    """Where the truth goes: the log sink, and the live Foxglove server if there is one."""

    def json(self, topic: str, t_ns: int, obj: dict[str, Any], schema_name: str = "") -> None:
        ...


class LiveView:
    """A sink that prints a pose line a second, scores poses against the truth, and puts the
    truth in the log (``/truth`` at each pose) so ``uwbd report`` can score the log too
    (and on the live Foxglove server, with ``--foxglove``)."""

    def __init__(self, scenario: CircleScenario, frame_id: str = "enu") -> None:
        self.scenario = scenario
        self.frame_id = frame_id
        self.outputs: list[JsonOutput] = []
        self.start_ns = time.time_ns()
        self.errors_m: list[float] = []
        self.last: Pose | None = None
        self._printed_ns = 0

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        """Not shown."""

    def frame(self, frame: Frame) -> None:
        """Not shown."""

    def pose(self, pose: Pose) -> None:
        self.last = pose
        t_s = (pose.t_ns - self.start_ns) / 1e9
        truth = self.scenario.position_m(t_s)
        if self.outputs:
            yaw = self.scenario.heading_rad(t_s)
            message = pose_message(pose.t_ns, truth,
                                   (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
                                   frame_id=self.frame_id)
            for output in self.outputs:
                output.json("/truth", pose.t_ns, message, "foxglove.PoseInFrame")
        self.errors_m.append(math.dist(pose.position_m[:2], truth[:2]))
        if pose.t_ns - self._printed_ns >= 1_000_000_000:
            self._printed_ns = pose.t_ns
            x, y, z = pose.position_m
            sx, sy = math.sqrt(pose.covariance[0]), math.sqrt(pose.covariance[7])
            speed = math.hypot(*pose.velocity_mps[:2])
            heading = "heading ok" if pose.heading_observable else "heading unknown"
            line = (f"{(pose.t_ns - self.start_ns) / 1e9:6.1f} s  pose ({x:6.2f}, {y:6.2f}, "
                    f"{z:5.2f}) m ±({sx:.2f}, {sy:.2f})  {speed:4.2f} m/s  {heading}  "
                    f"error {self.errors_m[-1]:.3f} m")
            try:
                print(line, flush=True)
            except BrokenPipeError:  # `uwbd demo | head`: the reader left; stop the demo
                quiet_stdout()
                os.kill(os.getpid(), signal.SIGTERM)

    def attach_log(self, log: McapSink) -> None:
        self.outputs.insert(0, log)

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        """The summary reads the final status from the pipeline."""

    def close(self) -> None:
        """Nothing to release."""


def run_demo(workdir: Path, duration_s: float | None, seed: int,
             live: Callable[[Config], Sink] | None = None, ros2_router: str | None = None) -> int:
    """Run until ``duration_s`` or Ctrl-C; returns 0. ``live`` makes a sink from the demo's
    config (``--foxglove``: the live server), which also gets the truth. ``ros2_router``:
    the ROS 2 topics on too, the session connected to that router (``--ros2``)."""
    devices = [DeviceSpec("imu", "wit", DEMO_FAULTS), DeviceSpec("uwb", "nlink", DEMO_FAULTS)]
    scenario = CircleScenario(seed=seed)
    log_dir = Path(tempfile.gettempdir()) / "uwbd-demo"
    sock = workdir / "zenoh.sock"
    emu = Emulator(devices, scenario, None, workdir)
    sources = [SourceConfig(d.name, d.driver, emu.ports[d.name].path, 921600) for d in devices]
    # the emulated sensors' specs, as a user would take them from the datasheets (their
    # antenna delays are exact and their range noise white: no range offsets or multipath
    # to estimate)
    rate = math.sqrt(scenario.imu_rate_hz)
    imu = {"acc_noise_mps2_rthz": scenario.acc_noise_mps2 / rate,
           "gyro_noise_rps_rthz": scenario.gyro_noise_rps / rate}
    text = to_toml(sources, dict(enumerate(scenario.anchors_m)),
                   ((1, 0, 0), (0, 1, 0), (0, 0, 1)), (0.0, 0.0, 0.0),
                   {"range_sigma_m": scenario.range_noise_m, "range_bias_states": False,
                    "multipath_sigma_m": 0.0}, imu)
    text += (f'\n[zenoh]\nprefix = "{PREFIX}"\nlisten = ["unixsock-stream/{sock}"]\n'
             "multicast_scouting = false\n")
    if ros2_router is not None:
        text += f'connect = ["{ros2_router}"]\n\n[ros2]\nenabled = true\n'

    config = parse(text, "demo config")
    view = LiveView(scenario, config.nav_frame_id)
    extra: list[Sink] = [view]
    if live is not None:
        try:
            server = live(config)  # before anything is said: a port in use ends the demo here
        except BaseException:
            emu.close()
            raise
        extra.append(server)
        if isinstance(server, JsonOutput):
            view.outputs.append(server)
    print(f"uwbd demo: emulated WitMotion IMU on {emu.ports['imu'].path}, Nooploop tag on "
          f"{emu.ports['uwb'].path}; the daemon fuses them. Ctrl-C to stop.\n"
          f"  follow it from another terminal: {echo_command(sock)}", flush=True)
    if ros2_router is not None:
        print(f"  as ROS 2 sees it: {echo_command(sock, ros2=True)} (or, with ROS 2 and its router "
              f"on {ros2_router}: ros2 topic echo /uwbd/pose)", flush=True)
    try:
        emu.start()
        view.start_ns = time.time_ns()
        pipeline = asyncio.run(run(config, log_dir, duration_s, extra_sinks=tuple(extra),
                                   on_log=view.attach_log))
    finally:
        with shielded():
            emu.close()
            for sink in extra[1:]:  # closed by the pipeline, unless it never ran
                sink.close()
    status = pipeline.status(time.time_ns())
    print("\nsummary:")
    for name, stats in status["parsers"].items():
        print(f"  {name}: {stats['frames']} frames, {stats['bytes_skipped']} bytes skipped, "
              f"{stats['checksum_errors']} checksum errors")
    print(f"  filter: {status['filter']}; {pipeline.poses} poses")
    if view.errors_m:
        rmse = math.sqrt(sum(e * e for e in view.errors_m) / len(view.errors_m))
        print(f"  fused pose vs scenario truth: XY RMSE {rmse:.3f} m over "
              f"{len(view.errors_m)} poses")
    files = [str(p) for sink in pipeline.sinks for p in getattr(sink, "files", [])]
    print(f"  log: {', '.join(files)}  (try: uwbd report {files[-1]})" if files else "  no log")
    sys.stdout.flush()
    return 0


def echo_command(sock: Path, ros2: bool = False) -> str:
    """The ``uwbd echo`` line that follows this demo (``ros2``: its ROS 2 pose topic), with
    the ``uwbd`` this one was started as (``.venv/bin/uwbd`` after the README's install)."""
    me = sys.argv[0] if Path(sys.argv[0]).name == "uwbd" else f"{sys.executable} -m uwbd"
    what = "--ros2" if ros2 else f"--prefix {PREFIX}"
    return f"{me} echo {what} --connect {shlex.quote(f'unixsock-stream/{sock}')}"
