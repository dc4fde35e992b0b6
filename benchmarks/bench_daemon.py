"""Daemon figures, measured side by side in one run.

    python benchmarks/bench_daemon.py [--seconds 15] [--runs 3] [--replay-s 586] [--replay-only]

* latency: serial read → Zenoh receive. A pose's ``t_ns`` is the time of the newest
  sample of the read that produced it (the read's receive time, ``time.time_ns()`` in the
  daemon; for a batched IMU read, put back by the bytes it carries past that sample:
  ``uwbd.service.sample_times``), so a subscriber on the same host takes
  ``time.time_ns() − t_ns`` on arrival: percentiles over every pose (from the sample, which
  is at most an IMU period older than the read);
* the floor under the CPU figure: what an asyncio loop that only wakes (60 and 200 times a
  second) costs on this machine;
* CPU (% of one core) and RSS of the ``uwbd run`` process, with the emulator (a process of
  its own, ``uwbd emulate``) feeding a 200 Hz WitMotion IMU and a 10 Hz Nooploop tag over
  pseudo-terminals, from ``/proc``; each run and the median of the runs;
* replay speed: a simulated log (about 10 minutes of a 200 Hz IMU and 6 anchors at 10 Hz,
  its reads as the daemon reads the devices: ``uwbd simulate``) through ``uwbd replay``'s
  pipeline, as a multiple of real time, without and with writing
  the output log; then the whole ``uwbd replay`` process (start-up, imports, reading the
  log, the replay), as a user runs it.

Each figure is taken twice in the same run, on the C core and on the pure-Python reference
(``UWBD_PURE_PYTHON=1``), and their ratio printed; the live one a third time with the
ROS 2 topics on (``[ros2] enabled``, a subscriber taking every sample), and what they add.
Everything stays on this machine: Zenoh on a unix socket, no scouting.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from uwbd.fusion.core import native
from uwbd.logs.reading import read_log
from uwbd.service.replay import replay
from uwbd.tools.logtools import write_simulation
from uwbd.tools.sim_presets import segments_for
from uwbd.tools.simulator import SimConfig, simulate

TICKS = os.sysconf("SC_CLK_TCK")
# the emulated vehicle stands this long before it drives off: the daemon starts meanwhile,
# levels and then tells its heading from the drive off (a daemon joining the steady circle
# later cannot, and would be measured aligning for good)
REST_S = 6.0
DEMO_CONFIG = Path(__file__).resolve().parents[1] / "config" / "demo.toml"


def config_text(imu: str, uwb: str, sock: Path) -> str:
    """``config/demo.toml`` (the emulated sensors' specs: with the generic defaults the
    heading σ of the emulated circle stays near 11°, above the 10° of "heading known", and
    the filter would be measured while "aligning") on these ports and this Zenoh socket."""
    text = DEMO_CONFIG.read_text()
    for old, new in (("/tmp/uwbd-emu/imu", imu), ("/tmp/uwbd-emu/uwb", uwb),
                     ("unixsock-stream//tmp/uwbd-emu/zenoh.sock", f"unixsock-stream/{sock}"),
                     ('prefix = "uwbd/demo"', 'prefix = "uwbd/bench"')):
        if old not in text:
            raise SystemExit(f"{DEMO_CONFIG}: no {old!r} to replace; update bench_daemon.py")
        text = text.replace(old, new)
    return text


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime + stime


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (threads of one name summed: Zenoh's runtime pools)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            name = (task / "comm").read_text().strip()
            name = name.rstrip("0123456789-") or name
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / TICKS
    return out


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


ROS2_SECTIONS = {"": "", "all": "\n[ros2]\nenabled = true\n",
                 "no IMU": '\n[ros2]\nenabled = true\nimu_topic = ""\n'}


def live(seconds: float, run: int, pure: bool, ros2: str = ""
         ) -> tuple[float, float, float, float]:
    """One live measurement; prints it and returns (p50 ms, p99 ms, CPU %, RSS MB).
    ``ros2``: the daemon also publishes its ROS 2 topics (``"all"``, or ``"no IMU"``), which
    a subscriber here takes as a ROS 2 node would, so that they are sent, not dropped for
    want of one (into a ring in Zenoh's own threads: no Python here competes for the cores
    per sample)."""
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sock = tmp / "z.sock"
        # the emulator in a process of its own, so the subscriber here is not kept from the
        # GIL by it (that was up to 0.5 ms of the measured latency)
        emulator = subprocess.Popen(
            [sys.executable, "-m", "uwbd", "emulate", "--uwb", "nlink", "--seed", "1",
             "--rest", str(REST_S), "--link-dir", str(tmp)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        daemon = None
        session = None
        latencies: list[int] = []
        try:
            while not (tmp / "imu").exists() or not (tmp / "uwb").exists():
                time.sleep(0.05)
            cfg = tmp / "cfg.toml"
            cfg.write_text(config_text(str(tmp / "imu"), str(tmp / "uwb"), sock)
                           + ROS2_SECTIONS[ros2])
            env = {k: v for k, v in os.environ.items() if k != native.PURE_PYTHON_ENV}
            if pure:
                env[native.PURE_PYTHON_ENV] = "1"
            daemon = subprocess.Popen(
                [sys.executable, "-m", "uwbd", "run", "-c", str(cfg), "--log-dir",
                 str(tmp / "logs")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                env=env)
            while not sock.exists():
                time.sleep(0.05)
            session = zenoh.open(zenoh.Config.from_json5(json.dumps({
                "mode": "peer", "connect": {"endpoints": [f"unixsock-stream/{sock}"]},
                "scouting": {"multicast": {"enabled": False}}})))

            phase = [""]

            def on_pose(sample: zenoh.Sample) -> None:
                now = time.time_ns()
                pose = json.loads(sample.payload.to_bytes())
                latencies.append(now - pose["t_ns"])
                phase[0] = pose["health"]["phase"]

            sub = session.declare_subscriber("uwbd/bench/pose", on_pose)
            ros_sub = (session.declare_subscriber("0/**", zenoh.handlers.RingChannel(1))
                       if ros2 else None)
            # start-up (imports, first fix, the heading told by the drive off) is not the
            # steady state: measured once tracking
            deadline = time.monotonic() + REST_S + 20.0
            while phase[0] != "tracking" and time.monotonic() < deadline:
                time.sleep(0.1)
            if phase[0] != "tracking":
                print(f"  (not tracking {REST_S + 20:.0f} s after the start but "
                      f"{phase[0] or 'no pose'}: measured so)")
            time.sleep(1.0)
            latencies.clear()
            cpu0, t0 = cpu_seconds(daemon.pid), time.monotonic()
            threads0 = thread_cpu_seconds(daemon.pid)
            ros0 = published(session)
            time.sleep(seconds)
            cpu1, t1 = cpu_seconds(daemon.pid), time.monotonic()
            threads1 = thread_cpu_seconds(daemon.pid)
            ros_rate = (published(session) - ros0) / (t1 - t0)
            rss = rss_mb(daemon.pid)
            sub.undeclare()
            if ros_sub is not None:
                ros_sub.undeclare()
        finally:
            if session is not None:
                session.close()
            for proc in (daemon, emulator):
                if proc is not None:
                    proc.send_signal(signal.SIGTERM)
                    proc.communicate(timeout=30)
        lat_ms = np.array(latencies) / 1e6
        p50, p99 = np.percentile(lat_ms, 50), np.percentile(lat_ms, 99)
        cpu = 100 * (cpu1 - cpu0) / (t1 - t0)
        name = variant_name(pure, ros2)
        print(f"live run {run} ({name}), {seconds:.0f} s: "
              "serial read -> Zenoh receive "
              f"p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {lat_ms.max():.2f} ms over "
              f"{len(lat_ms)} poses; daemon CPU {cpu:.2f} % of one core, RSS {rss:.0f} MB"
              + (f"; ROS 2 samples published {ros_rate:.0f}/s" if ros2 else ""))
        shares = sorted(((100 * (c - threads0.get(name, 0.0)) / (t1 - t0), name)
                         for name, c in threads1.items()), reverse=True)
        print("  by thread (% of one core): " + ", ".join(
            f"{name} {share:.1f}" for share, name in shares if share >= 0.05))
        return float(p50), float(p99), cpu, rss


def published(session: zenoh.Session) -> int:
    """The ROS 2 samples the daemon says it published so far (its status)."""
    for reply in session.get("uwbd/bench/status", timeout=2.0):
        if reply.ok is not None:
            return sum(json.loads(reply.ok.payload.to_bytes()).get("ros2", {})
                       .get("published", {}).values())
    return 0


def variant_name(pure: bool, ros2: str) -> str:
    return (("pure Python" if pure else "C core")
            + {"": "", "all": " + ROS 2 topics", "no IMU": " + ROS 2 topics but the IMU's"}[ros2])


def replay_speed(replay_s: float) -> None:
    sim = simulate(SimConfig(seed=1, segments=segments_for(replay_s)))
    duration_s = (sim.truth_t_ns[-1] - sim.truth_t_ns[0]) / 1e9
    with tempfile.TemporaryDirectory() as tmp_name:
        path = Path(tmp_name) / "sim.mcap"
        write_simulation(sim, path)
        contents = read_log(path)
        gc.freeze()  # as `uwbd replay` does: the log is not walked by every collection
        output = Path(tmp_name) / "o.mcap"
        for label, out in (("poses only", None), ("writing the output log", output)):
            speed = {}
            for impl in ("C core", "pure Python"):
                with native.pure_python() if impl == "pure Python" else contextlib.nullcontext():
                    t0 = time.perf_counter()
                    pipeline, _ = replay(contents, str(path), out)
                    elapsed = time.perf_counter() - t0
                speed[impl] = duration_s / elapsed
                print(f"replay, {duration_s:.0f} s simulated log, {label}, {impl}: "
                      f"{speed[impl]:.0f} x real time ({pipeline.poses} poses)")
            print(f"  C core / pure Python: {speed['C core'] / speed['pure Python']:.2f}")
        # the whole process, as a user runs it: start-up, imports (compiled once, as an
        # install leaves them: PYTHONDONTWRITEBYTECODE, set in some shells, would have every
        # start compile every module), reading the log, replay
        plain = {k: v for k, v in os.environ.items()
                 if k not in (native.PURE_PYTHON_ENV, "PYTHONDONTWRITEBYTECODE")}
        subprocess.run([sys.executable, "-m", "uwbd", "replay", str(path), "-o", str(output)],
                       check=True, env=plain, stdout=subprocess.DEVNULL)
        for label, extra in (("poses only", []), ("writing the output log", ["-o", str(output)])):
            whole = {}
            for impl in ("C core", "pure Python"):
                env = dict(plain)
                if impl == "pure Python":
                    env[native.PURE_PYTHON_ENV] = "1"
                output.unlink(missing_ok=True)
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "uwbd", "replay", str(path), *extra],
                               check=True, env=env, stdout=subprocess.DEVNULL)
                whole[impl] = time.perf_counter() - t0
                print(f"uwbd replay (the whole process), {label}, {impl}: {whole[impl]:.2f} s, "
                      f"{duration_s / whole[impl]:.0f} x real time")
            print(f"  C core / pure Python: {whole['pure Python'] / whole['C core']:.2f}")


def wakeup_floor(rate_hz: float, seconds: float = 8.0) -> float:
    """The CPU (% of one core) of an asyncio loop that does nothing but wake ``rate_hz``
    times a second for a pipe another process writes: what waking costs on this machine
    before any work (the daemon's loop wakes ~60 times a second, its reader thread once a
    read)."""
    r, w = os.pipe()
    os.set_blocking(r, False)
    writer = subprocess.Popen(
        [sys.executable, "-c", "import os, sys, time\nwhile True:\n"
         f"    time.sleep({1 / rate_hz}); os.write({w}, b'x')"], pass_fds=(w,))
    loop = asyncio.new_event_loop()
    try:
        loop.add_reader(r, lambda: os.read(r, 4096))
        loop.run_until_complete(asyncio.sleep(1.0))
        t0, wall0 = time.thread_time(), time.monotonic()
        loop.run_until_complete(asyncio.sleep(seconds))
        return 100 * (time.thread_time() - t0) / (time.monotonic() - wall0)
    finally:
        loop.close()
        writer.kill()
        writer.wait()
        os.close(r)
        os.close(w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="steady-state window")
    ap.add_argument("--runs", type=int, default=3,
                    help="live runs (a shared VM's CPU figures vary by ±1 point run to run)")
    ap.add_argument("--replay-s", type=float, default=586.0,
                    help="length of the replayed log (the default path repeated)")
    ap.add_argument("--replay-only", action="store_true", help="skip the live runs")
    ap.add_argument("--ros2-only", action="store_true",
                    help="only the live runs with and without the ROS 2 topics (C core)")
    args = ap.parse_args()
    if not args.replay_only:
        print("the floor: an empty asyncio loop woken by another process, "
              + ", ".join(f"{hz} times a second {wakeup_floor(hz):.2f} % CPU"
                          for hz in (60, 200)))
        live_runs(args.runs, args.seconds, args.ros2_only)
    if not args.ros2_only:
        replay_speed(args.replay_s)


def live_runs(count: int, seconds: float, only_ros2: bool = False) -> None:
    print("live: 200 Hz WitMotion IMU + 10 Hz Nooploop tag (6 anchors) on ptys")
    # (pure Python, ROS 2 topics) of each variant; alternated run by run, so that drifts of a
    # shared VM hit all alike
    ros2 = [(False, "all"), (False, "no IMU")]
    variants = [(False, ""), *ros2] if only_ros2 else [(False, ""), (True, ""), *ros2]
    runs: dict[tuple[bool, str], list[tuple[float, float, float, float]]] = {
        v: [] for v in variants}
    for k in range(count):
        for pure, topics in variants:
            runs[(pure, topics)].append(live(seconds, k + 1, pure, topics))
    medians = {}
    for (pure, topics), results in runs.items():
        medians[(pure, topics)] = np.median(np.array(results), axis=0)
        p50, p99, cpu, rss = medians[(pure, topics)]
        print(f"live, {variant_name(pure, topics)}, median of {count}: "
              f"p50 {p50:.2f} ms, p99 {p99:.2f} ms, CPU {cpu:.2f} %, RSS {rss:.0f} MB")
    if (True, "") in medians:
        print(f"  CPU, C core / pure Python: "
              f"{medians[(False, '')][2] / medians[(True, '')][2]:.2f}")
    for variant in ros2:
        added = [with_ros[2] - plain[2] for plain, with_ros in zip(
            runs[(False, "")], runs[variant], strict=True)]
        print(f"  CPU {variant_name(*variant).removeprefix('C core + ')} add (run by run, % of "
              f"one core): {', '.join(f'{a:+.2f}' for a in added)}; median "
              f"{np.median(added):+.2f}")


if __name__ == "__main__":
    main()
