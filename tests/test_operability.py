"""The service as an operator meets it: what every command says when something is wrong, and
that it never claims an output it did not write. Real subprocesses, ptys, Zenoh on unix
sockets, MCAP files, read-only and full file systems."""

from __future__ import annotations

import fcntl
import json
import os
import pty
import random
import selectors
import signal
import socket
import stat
import struct
import subprocess
import termios
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.writer import Writer
from procs import UNBUFFERED, UWBD, one_line, read_until, uwbd

from drivers import Frame, wit
from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import DEFAULT_ANCHORS_M, CircleScenario
from uwbd.config import parse
from uwbd.fusion.types import Pose
from uwbd.logs.mcaplog import LogWriter, SourceInfo
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.service.pipeline import Pipeline, PoseList
from uwbd.service.ports import ReadQueue
from uwbd.tools.logtools import simulation_toml, write_simulation
from uwbd.tools.simulator import DEFAULT_SEGMENTS, SimConfig, simulate

ANCHORS = "\n".join(f'"{i}" = [{x}, {y}, {z}]' for i, (x, y, z) in enumerate(DEFAULT_ANCHORS_M))


def config(tmp: Path, sources: dict[str, tuple[str, str]], extra: str = "") -> Path:
    """A daemon config: ``sources`` name -> (driver, port); Zenoh on a unix socket only."""
    text = "".join(f'[[sources]]\nname = "{n}"\ndriver = "{d}"\nport = "{p}"\nbaud = 921600\n\n'
                   for n, (d, p) in sources.items())
    text += f"[anchors]\n{ANCHORS}\n\n{extra}\n"
    text += (f'[zenoh]\nprefix = "uwbd/op"\nlisten = ["unixsock-stream/{tmp / "z.sock"}"]\n'
             "multicast_scouting = false\n")
    path = tmp / "cfg.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated run (raw device bytes + truth)."""
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    write_simulation(simulate(SimConfig(seed=5, segments=DEFAULT_SEGMENTS[:4])), path)
    return path


@pytest.fixture
def readonly_dir(tmp_path: Path) -> Iterator[Path]:
    """A folder nothing can be written into: a read-only tmpfs when we are root (root writes
    through file modes), else a folder with its write bit off."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() == 0:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs",
                                  str(folder)], capture_output=True, check=False)
        if mounted.returncode != 0:
            pytest.skip("running as root without mount: no folder is read-only to us")
        try:
            yield folder
        finally:
            subprocess.run(["umount", str(folder)], check=False)
    else:
        folder.chmod(0o500)
        try:
            yield folder
        finally:
            folder.chmod(0o700)


def foreign_mcap(path: Path) -> Path:
    """A valid MCAP file that uwbd did not write: no uwbd metadata, another topic."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        channel = w.register_channel("/chatter", "json", 0)
        w.add_message(channel, log_time=1, publish_time=1, data=b"{}")
        w.finish()
    return path


# -- commands that read a log ----------------------------------------------------------------

@pytest.mark.parametrize("command", ["replay", "report"])
@pytest.mark.parametrize(("make", "says"), [
    (lambda p: p.write_bytes(os.urandom(300)) and p, "not an MCAP file"),
    (lambda p: p.write_bytes(b"") or p, "the file is empty"),
    (lambda p: p.mkdir() or p, "is a folder"),
    (foreign_mcap, "not a uwbd log"),
    (lambda p: p, "no such file"),
])
def test_a_log_that_is_not_one_is_one_line_and_exit_2(tmp_path: Path, command: str,
                                                      make: Any, says: str) -> None:
    path = tmp_path / "in.mcap"
    make(path)
    result = uwbd(command, str(path), cwd=tmp_path)
    one_line(result, 2, str(path), says)
    assert not result.stdout  # no summary of a run that did not happen
    assert sorted(p.name for p in tmp_path.iterdir()) == (["in.mcap"] if path.exists() else [])


def test_recover_refuses_what_is_not_mcap_and_leaves_no_output(tmp_path: Path) -> None:
    garbage = tmp_path / "g.mcap"
    garbage.write_bytes(b"\x00" * 50)
    one_line(uwbd("recover", str(garbage), "-o", str(tmp_path / "out.mcap")), 2,
             "not an MCAP file")
    assert not (tmp_path / "out.mcap").exists()
    # the magic, then random bytes: no message to recover, said, exit 1, nothing written
    damaged = tmp_path / "d.mcap"
    damaged.write_bytes(b"\x89MCAP0\r\n" + random.Random(3).randbytes(20_000))
    one_line(uwbd("recover", str(damaged), "-o", str(tmp_path / "out.mcap")), 1,
             str(damaged), "no message could be recovered, nothing written")
    assert not (tmp_path / "out.mcap").exists()
    # any MCAP file is fine, uwbd's or not
    ok = uwbd("recover", str(foreign_mcap(tmp_path / "f.mcap")), "-o", str(tmp_path / "r.mcap"))
    assert ok.returncode == 0 and "1 messages recovered" in ok.stdout, ok.stderr


def _not_files(tmp_path: Path) -> list[Path]:
    """What ``-o`` must never write over nor remove: a FIFO, a folder, a socket and, as root,
    a character device (a twin of /dev/null, made here)."""
    fifo, folder, sock = tmp_path / "fifo", tmp_path / "folder", tmp_path / "sock"
    os.mkfifo(fifo)
    folder.mkdir()
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(sock))
    nodes = [fifo, folder, sock]
    if os.geteuid() == 0:
        null = tmp_path / "null"
        os.mknod(null, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        nodes.append(null)
    return nodes


def test_outputs_that_are_not_regular_files_are_refused_and_left_alone(
        tmp_path: Path, sim_log: Path) -> None:
    """#44: ``-o`` onto a device node, FIFO, socket or folder: one line, exit 2, before any
    work; the node is still there, of its kind; and a symlink to /dev/null is not followed."""
    nodes = _not_files(tmp_path)
    link = tmp_path / "to-null"
    link.symlink_to("/dev/null")
    before = {n: stat.S_IFMT(n.lstat().st_mode) for n in [*nodes, link]}
    for target in [*nodes, link]:
        for args in (("replay", str(sim_log), "-o", str(target)),
                     ("recover", str(sim_log), "-o", str(target)),
                     ("simulate", "--duration", "2", "-o", str(target)),
                     ("import", "inrol", str(tmp_path), "-o", str(target)),
                     ("survey", str(sim_log), "-o", str(target)),
                     ("calibrate-ranges", str(sim_log), "-o", str(target))):
            line = one_line(uwbd(*args, timeout=60), 2, str(target), "not a file")
            assert "give the path of a file" in line, line
    for target in nodes[:1] + nodes[2:]:  # a plots folder: anything but a folder is refused
        one_line(uwbd("report", str(sim_log), "-o", str(target), timeout=60), 2, str(target),
                 "not a folder")
    assert {n: stat.S_IFMT(n.lstat().st_mode) for n in [*nodes, link]} == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_failed_write_leaves_the_old_file_and_no_part(tmp_path: Path, sim_log: Path) -> None:
    """The output is written to a new file beside it and renamed over it whole: a command
    that fails leaves what was there before, and nothing of its own."""
    out = tmp_path / "out.mcap"
    out.write_bytes(b"an earlier run's log")
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(sim_log.read_bytes()[:400])  # the header only: nothing to recover
    one_line(uwbd("recover", str(damaged), "-o", str(out)), 1, "nothing written")
    assert out.read_bytes() == b"an earlier run's log"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged.mcap", "out.mcap"]
    ok = uwbd("recover", str(sim_log), "-o", str(out))
    assert ok.returncode == 0, ok.stderr
    assert out.read_bytes().startswith(b"\x89MCAP") and out.stat().st_mode & 0o777 != 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged.mcap", "out.mcap"]


def test_outputs_into_missing_or_read_only_folders_fail_before_work(
        tmp_path: Path, sim_log: Path, readonly_dir: Path) -> None:
    missing = tmp_path / "nope" / "out.mcap"
    result = one_line(uwbd("replay", str(sim_log), "-o", str(missing)), 2, str(missing),
                      "does not exist")
    assert "written to" not in result
    for args, target in [
        (("replay", str(sim_log), "-o", str(readonly_dir / "out.mcap")), "out.mcap"),
        (("simulate", "-o", str(readonly_dir / "s.mcap")), "s.mcap"),
        (("import", "inrol", str(tmp_path), "-o", str(readonly_dir / "i.mcap")), "i.mcap"),
        (("report", str(sim_log), "-o", str(readonly_dir / "plots")), "plots"),
        (("recover", str(sim_log), "-o", str(readonly_dir / "r.mcap")), "r.mcap"),
    ]:
        result = uwbd(*args)
        line = one_line(result, 2, target)
        assert "writ" in line and "written to" not in result.stdout, line
    assert list(readonly_dir.iterdir()) == []


def test_replay_with_other_settings_records_the_config_used(tmp_path: Path,
                                                           sim_log: Path) -> None:
    base = uwbd("replay", str(sim_log), "-o", str(tmp_path / "base.mcap"))
    tuned = uwbd("replay", str(sim_log), "-o", str(tmp_path / "tuned.mcap"),
                 "--set", "fusion.zupt=false", "--set", "fusion.range_sigma_m=0.3")
    assert base.returncode == 0 and tuned.returncode == 0, tuned.stderr
    used = parse(read_log(tmp_path / "tuned.mcap").metadata["config_toml"])
    assert used.fusion["zupt"] is False and used.fusion["range_sigma_m"] == 0.3
    assert parse(read_log(tmp_path / "base.mcap").metadata["config_toml"]).fusion.get(
        "zupt", True) is True
    # the source's truth goes along, so the replayed log can be scored in turn
    truth = list(read_log(sim_log).json("/truth"))
    assert list(read_log(tmp_path / "base.mcap").json("/truth")) == truth and truth

    def poses(name: str) -> list[Any]:
        return [d["pose"]["position"] for d in read_log(tmp_path / name).json("/pose")]
    assert poses("base.mcap") != poses("tuned.mcap")  # the settings took effect
    # a whole config file instead of the log's own (here: the log's, written out, in loose mode)
    still = SimConfig(seed=5, segments=((1.0, 0.0, 0.0, 0.0),))
    (tmp_path / "other.toml").write_text(simulation_toml(simulate(still)) + 'mode = "loose"\n')
    other = uwbd("replay", str(sim_log), "-c", str(tmp_path / "other.toml"),
                 "-o", str(tmp_path / "other.mcap"))
    assert other.returncode == 0, other.stderr
    assert 'mode = "loose"' in read_log(tmp_path / "other.mcap").metadata["config_toml"]
    # a setting that is not one: one line naming it, nothing written
    one_line(uwbd("replay", str(sim_log), "--set", "fusion.zupt=maybe",
                  "-o", str(tmp_path / "bad.mcap")), 2, "fusion.zupt")
    one_line(uwbd("replay", str(sim_log), "--set", "fusion.nonsense=1"), 2, "nonsense")
    assert not (tmp_path / "bad.mcap").exists()
    # a config whose sources the log does not have (or none): said, not 0 poses in silence
    (tmp_path / "empty.toml").write_text("")
    one_line(uwbd("replay", str(sim_log), "-c", str(tmp_path / "empty.toml")), 2,
             "its sources (none) name none of the log's (imu, uwb)")
    renamed = (tmp_path / "other.toml").read_text().replace('name = "imu"', 'name = "a"')
    (tmp_path / "renamed.toml").write_text(renamed.replace('name = "uwb"', 'name = "b"'))
    one_line(uwbd("replay", str(sim_log), "-c", str(tmp_path / "renamed.toml")), 2,
             "its sources (a, b) name none of the log's (imu, uwb)")


def test_report_without_truth_plots_what_it_can_and_says_nothing_raw(tmp_path: Path,
                                                                     sim_log: Path) -> None:
    """A log without /truth (a daemon's): the trajectory plotted, no error plot claimed, no
    plotting library's warning on stderr."""
    contents = read_log(sim_log)
    plain = tmp_path / "plain.mcap"
    sources = tuple(SourceInfo(**d) for d in json.loads(contents.metadata["sources"]))
    with LogWriter(plain, contents.metadata["config_toml"], sources) as log:
        for m in contents.messages:
            if m.topic.startswith("/raw/"):
                log.raw(m.topic[5:], m.log_time_ns, m.data)
    result = uwbd("report", str(plain), "-o", str(tmp_path / "plots"))
    assert result.returncode == 0, result.stderr
    assert result.stderr == "" and "no ground truth in this log" in result.stdout
    assert f"plots: {tmp_path / 'plots' / 'trajectory.png'}\n" in result.stdout
    assert not (tmp_path / "plots" / "error.png").exists()


def test_report_with_other_settings(tmp_path: Path, sim_log: Path) -> None:
    result = uwbd("report", str(sim_log), "-o", str(tmp_path / "plots"),
                  "--set", "fusion.range_sigma_m=0.2")
    assert result.returncode == 0, result.stderr
    assert "tight ESKF" in result.stdout and (tmp_path / "plots" / "error.png").is_file()


def test_replay_shows_progress_only_on_a_terminal(tmp_path: Path, sim_log: Path) -> None:
    piped = uwbd("replay", str(sim_log))
    assert piped.returncode == 0 and "replay:" not in piped.stderr, piped.stderr
    controller, terminal = pty.openpty()
    # a terminal has a size (a fresh pty's is 0 x 0, where a bar has no room)
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    shown = b""
    try:
        proc = subprocess.Popen([*UWBD, "replay", str(sim_log)], stdout=subprocess.DEVNULL,
                                stderr=terminal)
        os.close(terminal)
        deadline = time.monotonic() + 120
        with selectors.DefaultSelector() as sel:  # read as it runs: a pty drops the rest
            sel.register(controller, selectors.EVENT_READ)  # once its writer is gone
            while time.monotonic() < deadline:
                if not sel.select(1.0):
                    if proc.poll() is not None:
                        break
                    continue
                try:
                    chunk = os.read(controller, 65536)
                except OSError:  # EIO: the replay has ended
                    break
                if not chunk:
                    break
                shown += chunk
        proc.wait(timeout=10)
    finally:
        os.close(controller)
    assert proc.returncode == 0
    assert b"replay:" in shown and b"%" in shown


# -- the daemon -------------------------------------------------------------------------------

def test_daemon_with_no_ports_says_so_keeps_its_status_and_exits_1(tmp_path: Path) -> None:
    cfg = config(tmp_path, {"imu": ("wit", "/dev/ttyUSB97"), "uwb": ("nlink", "/dev/ttyUSB98")})
    journal = tmp_path / "journal.txt"
    with journal.open("w") as err:
        st = os.fstat(err.fileno())
        result = subprocess.run(
            [*UWBD, "run", "-c", str(cfg), "--log-dir", str(tmp_path / "logs"),
             "--duration", "3"], stdout=subprocess.PIPE, stderr=err, timeout=60, check=False,
            env={**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
    lines = journal.read_text().splitlines()
    assert result.returncode == 1 and "Traceback" not in journal.read_text()
    # journald reads the priority from each line; systemd adds the time
    assert all(line[:3] in ("<6>", "<4>", "<3>") for line in lines), lines
    text = "\n".join(lines)
    for needle in (f"with {cfg}", "source imu: wit on /dev/ttyUSB97", "anchors: 0 (",
                   "keys uwbd/op/{pose,status,alive}", f"logs: {tmp_path / 'logs'}",
                   "<4>uwbd run: warning: imu: cannot open /dev/ttyUSB97: No such file",
                   "<3>uwbd run: no port could be opened"):
        assert needle in text, (needle, text)
    # no byte arrived, and the status went on once a second all the same
    (log,) = (tmp_path / "logs").glob("*.mcap")
    statuses = list(read_log(log).json("/status"))
    assert len(statuses) >= 2
    assert statuses[-1]["sources"]["imu"]["state"] == "closed"
    quiet = uwbd("run", "-q", "-c", str(cfg), "--log-dir", str(tmp_path / "l2"),
                 "--duration", "0.5")
    assert "source imu" not in quiet.stderr and "warning: imu" in quiet.stderr


def test_daemon_says_when_every_range_is_rejected(tmp_path: Path) -> None:
    devices = [DeviceSpec("imu", "wit", Faults()), DeviceSpec("uwb", "nlink", Faults())]
    with Emulator(devices, CircleScenario(seed=1), duration_s=12.0, link_dir=tmp_path) as emu:
        # the anchors are 10-30 m away: a 2 m range limit lets nothing through
        cfg = config(tmp_path, {n: (d.driver, emu.ports[n].path) for n, d in
                                zip(("imu", "uwb"), devices, strict=True)},
                     "[fusion]\nmax_range_m = 2.0\n")
        daemon = subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir",
                                   str(tmp_path / "logs")], stderr=subprocess.PIPE,
                                  stdout=subprocess.DEVNULL, env=UNBUFFERED)
        try:
            read_until(daemon, b"uwb: opened", 20, "stderr")
            emu.start()
            said = read_until(daemon, b"every range rejected", 20, "stderr")
        finally:
            daemon.send_signal(signal.SIGTERM)
            daemon.communicate(timeout=20)
    assert b"too_long" in said


def _full_disk(folder: Path) -> list[str]:
    """Make ``folder`` small: a 400 kB tmpfs when we may mount (returns no wrapper), else a
    limit on the size of every file the daemon writes (``prlimit``; each new file has room
    again)."""
    if os.geteuid() == 0 and subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(folder)],
            capture_output=True, check=False).returncode == 0:
        return []
    return ["prlimit", "--fsize=150000"]


def test_log_stops_on_a_full_disk_finishes_the_file_and_resumes(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    wrapper = _full_disk(logs)
    tmpfs = not wrapper
    try:
        filler = logs / "filler"
        if tmpfs:  # leave ~120 kB: a few seconds of log
            filler.write_bytes(b"\0" * 280_000)
        devices = [DeviceSpec("imu", "wit", Faults()), DeviceSpec("uwb", "nlink", Faults())]
        with Emulator(devices, CircleScenario(seed=1), duration_s=60.0,
                      link_dir=tmp_path) as emu:
            cfg = config(tmp_path, {n: (d.driver, emu.ports[n].path) for n, d in
                                    zip(("imu", "uwb"), devices, strict=True)})
            daemon = subprocess.Popen([*wrapper, *UWBD, "run", "-c", str(cfg), "--log-dir",
                                       str(logs), "--summary-every", "2"], stderr=subprocess.PIPE,
                                      stdout=subprocess.DEVNULL, env=UNBUFFERED)
            try:
                read_until(daemon, b"uwb: opened", 20, "stderr")
                emu.start()
                stopped = read_until(daemon, b"logging stopped", 40, "stderr")
                if tmpfs:
                    filler.unlink()  # room again
                resumed = read_until(daemon, b"logging resumed into", 20, "stderr")
                time.sleep(1.5)
            finally:
                daemon.send_signal(signal.SIGTERM)
                _, rest = daemon.communicate(timeout=20)
        assert daemon.returncode == 0, rest
        assert b"is finished with what was written before" in stopped
        said = stopped + resumed + rest
        # the daemon's running commentary, as the journal gets it
        assert b"first pose: (" in said and b"poses/s; ranges " in said
        # the phase: with the first pose, and each change (a status may or may not have
        # caught the filter still waiting before its first pose: that depends on timing)
        assert b" m, aligning" in said or b"filter waiting -> aligning" in said
        files = sorted(logs.glob("*.mcap"))
        assert len(files) >= 2
        for path in files:  # every file finished: no crash recovery needed
            contents = read_log(path)
            assert not contents.truncated, (path, contents.error)
            assert contents.metadata["config_toml"]
        first, last = read_log(files[0]), read_log(files[-1])
        assert len(list(first.json("/pose"))) > 20 and len(list(last.json("/pose"))) > 20
        assert b"Traceback" not in stopped + resumed + rest
    finally:
        if tmpfs:
            subprocess.run(["umount", str(logs)], check=False)


def test_kill_9_of_a_uwb_only_run_keeps_all_but_the_last_second(tmp_path: Path) -> None:
    """At 10 Hz of ranges a chunk takes minutes to fill: only the periodic flush saves it."""
    devices = [DeviceSpec("uwb", "nlink", Faults())]
    with Emulator(devices, CircleScenario(seed=1), duration_s=20.0, link_dir=tmp_path) as emu:
        cfg = config(tmp_path, {"uwb": ("nlink", emu.ports["uwb"].path)})
        daemon = subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir",
                                   str(tmp_path / "logs")], stderr=subprocess.PIPE,
                                  stdout=subprocess.DEVNULL, env=UNBUFFERED)
        try:
            read_until(daemon, b"uwb: opened", 20, "stderr")
            emu.start()
            time.sleep(4.0)
        finally:
            killed_ns = time.time_ns()
            daemon.send_signal(signal.SIGKILL)
            daemon.communicate(timeout=10)
    (log,) = (tmp_path / "logs").glob("*.mcap")
    contents = read_log(log)
    assert contents.truncated
    ranges = [m.log_time_ns for m in contents.messages if m.topic == "/raw/uwb"]
    assert len(ranges) >= 20
    assert (killed_ns - max(ranges)) / 1e9 < 1.6


class BuggyParser(wit.WitParser):
    """A WitMotion parser with a bug: it raises on a read holding ``BUG``."""

    def feed(self, data: bytes, t_ns: int) -> list[Frame]:
        if b"BUG" in data:
            raise ZeroDivisionError("a bug")
        return list(super().feed(data, t_ns))


def test_a_pipeline_that_raises_stops_the_reads_and_says_so(
        sim_log: Path, caplog: pytest.LogCaptureFixture) -> None:
    contents = read_log(sim_log)
    pipeline = Pipeline(parse(contents.metadata["config_toml"]), [PoseList()])
    pipeline.parsers["imu"] = BuggyParser()
    queue = ReadQueue(pipeline)
    raw = [m for m in contents.messages if m.topic.startswith("/raw/")][:500]
    with caplog.at_level("ERROR", logger="uwbd"):
        for m in raw[:200]:
            queue.push(m.topic[5:], m.log_time_ns, m.data)
        queue.push("imu", raw[200].log_time_ns, b"BUG")
        for m in raw[201:]:
            queue.push(m.topic[5:], m.log_time_ns, m.data)
        queue.flush()
    assert isinstance(queue.failure, ZeroDivisionError)
    before = pipeline.parsers["uwb"].stats.frames
    queue.push("uwb", raw[-1].log_time_ns + 1, raw[-1].data)
    queue.flush()
    assert pipeline.parsers["uwb"].stats.frames == before  # nothing more goes in
    (record,) = caplog.records
    assert "the pipeline failed on a read of imu: ZeroDivisionError: a bug" in record.getMessage()


# -- sinks -------------------------------------------------------------------------------------

class Broken:
    """A sink that raises on everything."""

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        raise RuntimeError("raw broke")

    def frame(self, frame: Frame) -> None:
        raise RuntimeError("frame broke")

    def pose(self, pose: Pose) -> None:
        raise ValueError("pose broke")

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        raise RuntimeError("status broke")

    def close(self) -> None:
        raise RuntimeError("close broke")


class Frames(PoseList):
    """A sink of raw and frame calls only (no ``read``): it keeps them in order."""

    def __init__(self, raw_fails: bool = False) -> None:
        super().__init__()
        self.raw_fails = raw_fails
        self.calls: list[Any] = []

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        if self.raw_fails:
            raise RuntimeError("raw broke")
        self.calls.append((source, t_ns, data))

    def frame(self, frame: Frame) -> None:
        self.calls.append(frame)


def test_a_sink_without_read_gets_raw_and_frame_each_guarded(sim_log: Path) -> None:
    """A sink that has no ``read`` gets a read the C core took whole as its raw call and its
    frame call, in order; its raw failing keeps it from no frame."""
    works, fails = Frames(), Frames(raw_fails=True)
    pipeline = _run(sim_log, [works, fails])
    frames = [c for c in works.calls if not isinstance(c, tuple)]
    assert fails.calls == frames and len(frames) > 1000
    raws = [c for c in works.calls if isinstance(c, tuple)]
    assert isinstance(works.calls[0], tuple) and len(raws) > 1000
    (trouble,) = pipeline.sink_trouble.values()
    assert trouble.failures == len(raws) and "raw broke" in trouble.last_error


def test_a_read_that_breaks_the_pipeline_is_still_logged(sim_log: Path) -> None:
    """A read's bytes reach the sinks before a bug on it stops the pipeline: the log shows
    the read that broke it."""
    contents = read_log(sim_log)
    sink = Frames()
    pipeline = Pipeline(parse(contents.metadata["config_toml"]), [sink])
    pipeline.parsers["imu"] = BuggyParser()
    for m in contents.messages[:300]:
        if m.topic.startswith("/raw/"):
            pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
    with pytest.raises(ZeroDivisionError):
        pipeline.on_bytes("imu", m.log_time_ns + 1, b"BUG")
    assert sink.calls[-1] == ("imu", m.log_time_ns + 1, b"BUG")


def _run(sim_log: Path, sinks: list[Any]) -> Pipeline:
    contents = read_log(sim_log)
    pipeline = Pipeline(parse(contents.metadata["config_toml"]), sinks)
    for m in contents.messages:
        if m.topic.startswith("/raw/"):
            pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
    pipeline.finish()
    pipeline.close()
    return pipeline


def test_a_failing_sink_costs_the_others_nothing(tmp_path: Path, sim_log: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    alone = PoseList()
    _run(sim_log, [alone])
    config = parse(read_log(sim_log).metadata["config_toml"])
    beside, log = PoseList(), McapSink(config, path=tmp_path / "out.mcap")
    with caplog.at_level("WARNING", logger="uwbd"):
        pipeline = _run(sim_log, [Broken(), beside, log])
    assert beside.poses == alone.poses and len(alone.poses) > 100
    contents = read_log(tmp_path / "out.mcap")
    assert not contents.truncated and len(list(contents.json("/pose"))) == len(alone.poses)
    (trouble,) = pipeline.sink_trouble.values()
    assert trouble.name == "Broken" and trouble.failures > 1000
    assert any("Broken failed" in e for e in beside.statuses[-1]["sink_errors"])
    warned = [r.getMessage() for r in caplog.records]
    assert any("raw broke" in w for w in warned) and any("pose broke" in w for w in warned)


def test_a_record_the_log_cannot_encode_is_counted_and_skipped(tmp_path: Path) -> None:
    log = McapSink(parse(""), path=tmp_path / "x.mcap")
    log.json("/a", 1, {"ok": 1})
    log.json("/a", 2, {"not json": {1, 2}})  # a set: json cannot encode it
    log.json("/a", 3, {"ok": 3})
    log.close()
    assert log.bad_records == 1
    assert [d["ok"] for d in read_log(tmp_path / "x.mcap").json("/a")] == [1, 3]


# -- demo, echo, emulate ---------------------------------------------------------------------

def test_demo_into_head_ends_quietly() -> None:
    started = time.monotonic()
    result = subprocess.run(f"{' '.join(UWBD)} demo --duration 30 | head -3", shell=True,
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    assert len(result.stdout.splitlines()) == 3
    assert time.monotonic() - started < 20  # it stopped when its reader left


def test_demo_says_how_to_follow_it_and_echo_finds_it(tmp_path: Path) -> None:
    demo = subprocess.Popen([*UWBD, "demo", "--duration", "40"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, env=UNBUFFERED)
    try:
        head = read_until(demo, b"follow it from another terminal: ", 20)
        if not head.split(b"follow it from another terminal: ")[1].count(b"\n"):
            head += read_until(demo, b"\n", 5)
        line = next(x for x in head.decode().splitlines() if "follow it" in x)
        printed = line.split("terminal: ", 1)[1]
        command = printed.split()
        assert "echo" in command and "--connect" in command
        sock = command[command.index("--connect") + 1]
        read_until(demo, b"pose (", 20)
        # the line as printed, run as printed
        got = subprocess.run(f"{printed} --count 2", shell=True, capture_output=True, text=True,
                             timeout=30, check=False)
        assert got.returncode == 0 and len(got.stdout.splitlines()) == 2, got.stderr
        # a wildcard: each line says which robot it came from
        fleet = uwbd("echo", "--prefix", "uwbd/*", "--connect", sock, "--count", "2")
        lines = fleet.stdout.splitlines()
        assert fleet.returncode == 0 and len(lines) == 2, fleet.stderr
        assert all(x.startswith("uwbd/demo/pose  ") for x in lines)
        # the wrong prefix: said within seconds, with the daemons that are there
        wrong = uwbd("echo", "--prefix", "uwbd/other", "--connect", sock, "--timeout", "5")
        assert wrong.returncode == 1 and "Traceback" not in wrong.stderr
        assert "daemons seen: uwbd/demo" in wrong.stderr and "nothing received" in wrong.stderr
        # -c: the daemon's own config; echo dials its listen endpoint
        cfg = tmp_path / "daemon.toml"
        cfg.write_text(f'[zenoh]\nprefix = "uwbd/demo"\nlisten = ["{sock}"]\n'
                       "multicast_scouting = false\n")
        by_config = uwbd("echo", "-c", str(cfg), "--count", "1", "--timeout", "10")
        assert by_config.returncode == 0 and "p=(" in by_config.stdout, by_config.stderr
    finally:
        demo.send_signal(signal.SIGINT)
        demo.communicate(timeout=20)


def test_emulate_creates_its_link_folder(tmp_path: Path) -> None:
    links = tmp_path / "new" / "emu"
    result = uwbd("emulate", "--link-dir", str(links), "--duration", "0.5")
    assert result.returncode == 0, result.stderr
    assert f"{links / 'imu'}" in result.stdout and links.is_dir()


def test_the_readme_walk_through_works_as_written() -> None:
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    block = readme.split("<!-- walkthrough")[1].split("```sh\n")[1].split("```")[0]
    emulate, run, echo = (line.replace(".venv/bin/uwbd", " ".join(UWBD)).split()
                          for line in block.strip().splitlines())
    root = Path(__file__).parents[1]
    procs = [subprocess.Popen(emulate, cwd=root, stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, env=UNBUFFERED)]
    try:
        read_until(procs[0], b"uwb", 20)
        procs.append(subprocess.Popen(run, cwd=root, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, env=UNBUFFERED))
        read_until(procs[1], b"uwb: opened", 20, "stderr")
        got = subprocess.run([*echo, "--count", "3", "--timeout", "20"], cwd=root,
                             capture_output=True, text=True, timeout=40, check=False)
        assert got.returncode == 0 and len(got.stdout.splitlines()) == 3, got.stderr
        assert all("p=(" in line for line in got.stdout.splitlines())
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=20)
    assert procs[1].returncode == 0


def test_echo_with_nothing_there_or_a_bad_prefix_says_so(tmp_path: Path) -> None:
    gone = f"unixsock-stream/{tmp_path / 'nobody.sock'}"
    one_line(uwbd("echo", "--connect", gone, "--timeout", "3"), 1, "cannot reach", gone,
             "is the daemon (uwbd run) or the router running there?")
    one_line(uwbd("echo", "--prefix", "uwbd/a?b", "--timeout", "1"), 2,
             "--prefix uwbd/a?b: not a key expression")


def test_output_into_head_ends_quietly(tmp_path: Path, sim_log: Path) -> None:
    capture = Path(__file__).parent / "data" / "wit-GARBAGE.bin"
    for command in (f"dump --driver wit {capture}", f"replay {sim_log}", "--help"):
        result = subprocess.run(f"{' '.join(UWBD)} {command} | head -c 20", shell=True,
                                capture_output=True, text=True, timeout=60, check=False)
        assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
        assert "Exception ignored" not in result.stderr


@pytest.mark.parametrize("config", ["", '[anchors]\n"1" = [0, 0, 2]\n"2" = [5, 0, 2]\n'])
def test_a_full_disk_pauses_the_log_and_every_record_is_accounted_for(
        small_disk: Path, config: str) -> None:
    """Retries while the disk is still full claim nothing and leave no junk; once there is
    room the log resumes; every record is either in a finished file or counted lost,
    exactly (#44: with anchors, each new file's scene record is not one of them)."""
    folder = small_disk
    filler = folder / "filler"
    filler.write_bytes(b"\0" * 150_000)
    log = McapSink(parse(config), directory=folder)
    t_ns, written, states = 1_700_000_000 * 10**9, 0, []
    for k in range(3000):  # 30 s of data at 100 records/s
        if k == 2000:
            filler.unlink()  # room again
        # incompressible until the disk is full, then small, so it does not fill again
        pad = os.urandom(200 if k < 2000 else 4).hex()
        log.json("/a", t_ns, {"k": k, "pad": pad})
        written += 1
        t_ns += 10_000_000
        states.append(bool(log.error))
    log.close()
    assert True in states[:2000] and states[-1] is False  # paused while full, then not
    paused = states.index(True)
    assert all(states[paused:2000])  # no retry in between claimed to have resumed
    files = [p for p in log.files if p.exists()]
    assert files == log.files  # every file it names is there: no half-made ones dropped
    assert sorted(folder.glob("*.mcap")) == sorted(files)
    kept = 0
    for path in files:  # each one finished: no recovery needed
        contents = read_log(path)
        assert not contents.truncated, contents.error
        kept += sum(m.topic == "/a" for m in contents.messages)
    assert kept + log.records_lost == written and log.records_lost > 0


def test_a_full_disk_counts_every_record_a_pose_writes(small_disk: Path, sim_log: Path,
                                                        tmp_path: Path) -> None:
    """A pose is /pose, /tf and now and then /trajectory: on a disk that fills, the records
    kept and those counted lost add up to what a log with room holds (it counted one)."""
    contents = read_log(sim_log)
    poses = PoseList()
    pipeline = Pipeline(parse(contents.metadata["config_toml"]), [poses])
    for m in contents.messages:
        if m.topic.startswith("/raw/"):
            pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
    topics = ("/pose", "/tf", "/trajectory")

    def run(folder: Path, fill: bool) -> tuple[int, int, int]:
        """Records kept in the files, written /a padding, records counted lost."""
        log, padding = McapSink(parse(""), directory=folder), 0
        for k, pose in enumerate(poses.poses):
            if fill and k == 2 * len(poses.poses) // 3:
                (folder / "filler").unlink()  # room again
            log.pose(pose)
            if fill and k < 2 * len(poses.poses) // 3:  # incompressible: the disk fills
                log.json("/a", pose.t_ns, {"pad": os.urandom(300).hex()})
                padding += 1
        log.close()
        assert all(read_log(path).messages for path in log.files), log.files  # none empty
        kept = sum(m.topic in (*topics, "/a") for path in log.files
                   for m in read_log(path).messages)
        return kept, padding, log.records_lost

    (tmp_path / "roomy").mkdir()
    whole, _, none_lost = run(tmp_path / "roomy", False)
    assert none_lost == 0 and whole > 2 * len(poses.poses)  # /trajectory among them
    (small_disk / "filler").write_bytes(b"\0" * 150_000)
    kept, padding, lost = run(small_disk, True)
    assert lost > 0 and kept + lost == whole + padding


def test_a_damaged_chunk_is_said_and_what_came_before_is_used(tmp_path: Path,
                                                              sim_log: Path) -> None:
    data = bytearray(sim_log.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = os.urandom(64)  # inside a compressed chunk
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    replayed = uwbd("replay", str(damaged))
    assert replayed.returncode == 0 and "Traceback" not in replayed.stderr, replayed.stderr
    assert "internal error" not in replayed.stderr and "damaged" in replayed.stderr
    assert "poses" in replayed.stdout
    fixed = uwbd("recover", str(damaged), "-o", str(tmp_path / "fixed.mcap"))
    assert fixed.returncode == 0 and "damaged stretch" in fixed.stdout, fixed.stderr
    assert not read_log(tmp_path / "fixed.mcap").truncated


def test_a_damaged_truth_record_is_counted_and_the_replay_goes_on(tmp_path: Path,
                                                                   sim_log: Path) -> None:
    """A /truth record that is not JSON (a damaged or foreign log): ``replay -o`` says so
    once, counts it, and writes everything else (it raised before)."""
    contents = read_log(sim_log)
    spoilt = [k for k, m in enumerate(contents.messages) if m.topic == "/truth"][10]
    damaged = tmp_path / "damaged.mcap"
    with damaged.open("wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("uwbd", contents.metadata)
        channels: dict[str, int] = {}
        for k, m in enumerate(contents.messages):
            if m.topic not in channels:
                encoding = "json" if m.topic == "/truth" else "uwbd.raw"
                channels[m.topic] = w.register_channel(m.topic, encoding, 0)
            data = b"{not json" if k == spoilt else m.data
            w.add_message(channels[m.topic], log_time=m.log_time_ns,
                          publish_time=m.log_time_ns, data=data)
        w.finish()
    out = tmp_path / "out.mcap"
    result = uwbd("replay", str(damaged), "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert "/truth record" in result.stderr and "not JSON; skipped" in result.stderr
    truth_in = sum(m.topic == "/truth" for m in contents.messages)
    replayed = read_log(out)
    assert sum(m.topic == "/truth" for m in replayed.messages) == truth_in - 1
    assert list(replayed.json("/status"))[-1]["bad_records"] == 1


def test_a_foreign_log_with_uwbds_topic_names_is_said_to_be_one(tmp_path: Path) -> None:
    """Another program's MCAP with /imu and /uwb channels of its own JSON: each command that
    runs a log says so in one line, exit 2 (was: an internal error, or 0 poses in silence)."""
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("x", "jsonschema", b"{}")
        channels = [w.register_channel(t, "json", schema) for t in ("/imu", "/uwb")]
        for k in range(60):
            for c in channels:
                t_ns = 10**18 + k * 5_000_000
                w.add_message(c, t_ns, b'{"foo": %d}' % k, t_ns)
        w.finish()
    config = tmp_path / "sim.toml"
    config.write_text(simulation_toml(simulate(SimConfig(seed=5,
                                                         segments=((1.0, 0.0, 0.0, 0.0),)))))
    for command in (("replay", "-c", str(config)), ("report", "-c", str(config), "-o",
                                                     str(tmp_path / "plots")),
                    ("export", "-c", str(config), "--ros2", str(tmp_path / "bag"))):
        one_line(uwbd(command[0], str(foreign), *command[1:]), 2, str(foreign),
                 "not uwbd's frames", "another program's log")
    assert not (tmp_path / "plots").exists() and not (tmp_path / "bag").exists()
    calibration = uwbd("calibrate-imu", str(foreign))
    assert calibration.returncode == 2
    assert "120 of 120 /imu, /uwb records are not frames" in calibration.stderr
    assert "no IMU samples" in calibration.stderr and "internal error" not in calibration.stderr
