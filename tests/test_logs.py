"""MCAP logs and the fusion commands, as real files and subprocesses."""

from __future__ import annotations

import itertools
import json
import math
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zstandard
from hypothesis import example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Message

from drivers.frames import ImuSample, UwbRanges
from uwbd.codec import frame_to_json, strict_json
from uwbd.config import parse
from uwbd.fusion.core.rotation import quat_to_matrix
from uwbd.logs import foxglove as fx
from uwbd.logs import intact, reading, scan
from uwbd.logs.mcaplog import UNENCODABLE, LogWriter, SourceInfo
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.tools.importer import INROL_EPOCH_NS
from uwbd.tools.logtools import load_recording, write_simulation
from uwbd.tools.simulator import EPOCH_NS, SimConfig, simulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "iasl-s1"
INROL = DATA.parent / "inrol-env1"
UWBD = [sys.executable, "-m", "uwbd"]
SHORT = ((3.0, 0.0, 0.0, 0.0), (4.0, 1.0, 0.2, 0.0), (2.0, 0.0, 0.0, 0.0))


def uwbd(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*UWBD, *args], capture_output=True, text=True, timeout=120,
                          check=False, cwd=cwd, env={**os.environ, "MPLBACKEND": "Agg"})


def test_simulated_log_replays_through_the_drivers(tmp_path: Path) -> None:
    sim = simulate(SimConfig(segments=SHORT, seed=2))
    path = tmp_path / "sim.mcap"
    write_simulation(sim, path, "dwm1001-tlv")
    contents = read_log(path)
    assert not contents.truncated
    assert {"/raw/imu", "/raw/uwb", "/truth"} <= contents.topics()
    rec = load_recording(contents, str(path))
    imu = [f for f in rec.frames if isinstance(f, ImuSample)]
    uwb = [f for f in rec.frames if isinstance(f, UwbRanges)]
    assert len(imu) == len(sim.imu) and len(uwb) == len(sim.uwb)
    # the same times: the IMU's batched reads, stamped inside the next report, put back by
    # the bytes they carry past their last whole sample and spread over the learned period
    # (all but the tail after the last read, read late); values within the wire formats'
    # resolution
    late_ns = [a.t_ns - b.t_ns for a, b in zip(imu, sim.imu, strict=True)]
    assert max(abs(d) for d in late_ns[:-4]) < 1_000  # ns (a byte's time, rounded)
    assert all(b.t_ns > a.t_ns for a, b in itertools.pairwise(imu))
    assert all(abs(a.acc_mps2[2] - b.acc_mps2[2]) < 0.005 for a, b in zip(imu, sim.imu,
                                                                          strict=True))
    assert all(abs(a.ranges[0].range_m - b.ranges[0].range_m) < 0.0006
               for a, b in zip(uwb, sim.uwb, strict=True))
    assert rec.config.anchors_m == dict(enumerate(sim.config.anchors_m))
    assert all(s["bytes_skipped"] == 0 for s in rec.parser_stats.values())
    assert len(rec.truth_t_ns) > 100


def test_a_log_cut_short_by_a_crash_still_reads(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    with LogWriter(path, sources=(SourceInfo("uwb", "nlink"),), chunk_bytes=1024) as log:
        for k in range(2000):
            log.raw("uwb", k * 10**7, bytes(64))
            if k % 100 == 99:
                log.flush()
    data = path.read_bytes()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])  # no footer, a torn chunk at the end
    contents = read_log(cut)
    assert contents.truncated and "crashed.mcap" in contents.error
    assert 1000 <= len(contents.messages) < 2000
    assert [m.log_time_ns for m in contents.messages] == [
        k * 10**7 for k in range(len(contents.messages))]
    # `uwbd recover` writes what survived as a finished file that a seeking reader opens
    fixed = tmp_path / "fixed.mcap"
    result = uwbd("recover", str(cut), "-o", str(fixed))
    assert result.returncode == 0, result.stderr
    assert f"{len(contents.messages)} messages recovered" in result.stdout
    assert "ends mid-record" in result.stdout
    with fixed.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        times = [m.log_time for _, _, m in reader.iter_messages()]
        assert times == [m.log_time_ns for m in contents.messages]
        assert "uwbd" in {r.name for r in reader.iter_metadata()}
    assert not read_log(fixed).truncated


def test_simulate_then_report_as_commands(tmp_path: Path) -> None:
    sim = uwbd("simulate", "-o", "s.mcap", "--seed", "1", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    rep = uwbd("report", "s.mcap", "--skip", "8", cwd=tmp_path)
    assert rep.returncode == 0, rep.stderr
    rows = {line.split("  ")[0].strip(): line.split() for line in rep.stdout.splitlines()
            if ("ESKF" in line and "NIS" not in line) or "least squares" in line}
    tight_xy, ls_xy = float(rows["tight ESKF"][-5]), float(rows["uwb least squares"][-5])
    assert tight_xy < 0.08 and tight_xy < 0.6 * ls_xy
    assert (tmp_path / "s" / "trajectory.png").stat().st_size > 10_000
    assert (tmp_path / "s" / "error.png").stat().st_size > 10_000


@pytest.mark.skipif(not DATA.is_dir(), reason="shared/data not beside the repository")
def test_import_real_flight_then_report(tmp_path: Path) -> None:
    imp = uwbd("import", "iasl", str(DATA), "-o", "f.mcap", cwd=tmp_path)
    assert imp.returncode == 0, imp.stderr
    rep = uwbd("report", "f.mcap", cwd=tmp_path)
    assert rep.returncode == 0, rep.stderr
    assert "without its 1 motion-capture spike" in rep.stdout
    clean = rep.stdout.split("without its")[1]
    tight = next(line for line in clean.splitlines() if line.startswith("tight ESKF")).split()
    assert float(tight[2]) < 0.07 and float(tight[4]) < 0.12  # XY, 3D


def test_fusion_commands_fail_clearly(tmp_path: Path) -> None:
    missing = uwbd("report", "nope.mcap", cwd=tmp_path)
    assert missing.returncode == 2 and "nope.mcap" in missing.stderr
    bad = uwbd("import", "iasl", str(tmp_path), cwd=tmp_path)
    assert bad.returncode == 2 and "imu.csv" in bad.stderr
    gone = uwbd("recover", "nope.mcap", "-o", "out.mcap", cwd=tmp_path)
    assert gone.returncode == 2 and "nope.mcap" in gone.stderr


INROL_FILES = {
    "anchor.txt": """# anchor_id tx ty tz qx qy qz qw
1 0.0 0.0 0.3 0.5 0.5 0.5 -0.5
3 4.0 0.0 2.3 0.5 -0.5 0.5 0.5
2 0.0 4.0 0.3 0.0 0.0 0.0 1.0
""",
    "imu.txt": """# index timestamp wx wy wz ax ay az
0 0.005000000000 0.01 0.02 0.03 0.1 0.2 9.8
1 0.015000000000 0.01 0.02 0.03 0.1 0.2 9.8
2 0.025000000000 0.01 0.02 0.03 0.1 0.2 9.8
""",
    # two ranges share a stamp; one line is out of time order, as in the real run
    "uwb.txt": """# index timestamp anchor_id r
0 0.100000000000 1 2.0
1 0.100000000000 2 3.0
2 0.110000000000 3 4.0
3 0.123456789123 1 2.1
4 0.120000000000 2 3.1
""",
    "imu_pose.txt": """# timestamp tx ty tz qx qy qz qw
0.000000000000 1.0 2.0 0.5 0.0 0.0 0.0 1.0
0.010000000000 1.0 2.0 0.5 0.0 0.0 0.707106781187 0.707106781187
""",
}


def inrol_dir(root: Path, **replace: str) -> Path:
    """A tiny dataset in the inrol layout; ``replace`` swaps a file's text (``""``: none)."""
    root.mkdir()
    for name, text in {**INROL_FILES, **replace}.items():
        if text:
            (root / name).write_text(text)
    return root


def test_import_inrol_layout_as_a_command(tmp_path: Path) -> None:
    imp = uwbd("import", "inrol", str(inrol_dir(tmp_path / "run")), "-o", "i.mcap",
               cwd=tmp_path)
    assert imp.returncode == 0, imp.stderr
    assert "3 IMU samples, 4 UWB messages (5 ranges), 2 truth samples" in imp.stdout
    contents = read_log(tmp_path / "i.mcap")
    rec = load_recording(contents, "i.mcap")
    imu = [f for f in rec.frames if isinstance(f, ImuSample)]
    uwb = [f for f in rec.frames if isinstance(f, UwbRanges)]
    assert INROL_EPOCH_NS == EPOCH_NS  # the simulator's epoch
    assert [f.t_ns - INROL_EPOCH_NS for f in imu] == [5_000_000, 15_000_000, 25_000_000]
    assert imu[0].acc_mps2 == (0.1, 0.2, 9.8) and imu[0].gyro_rps == (0.01, 0.02, 0.03)
    # equal stamps make one message, others one each, in time order; exact nanoseconds
    assert [(m.t_ns - INROL_EPOCH_NS, [(r.anchor_id, r.range_m) for r in m.ranges])
            for m in uwb] == [(100_000_000, [(1, 2.0), (2, 3.0)]), (110_000_000, [(3, 4.0)]),
                              (120_000_000, [(2, 3.1)]), (123_456_789, [(1, 2.1)])]
    assert rec.config.anchors_m == {1: (0.0, 0.0, 0.3), 2: (0.0, 4.0, 0.3),
                                    3: (4.0, 0.0, 2.3)}
    assert rec.config.mounting == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    assert rec.config.lever_arm_m == (0.0, 0.0, 0.01)
    assert rec.config.fusion == {}  # the filter's defaults: tight, one range at a time
    truth = list(contents.json("/truth"))
    assert [d["t_ns"] - INROL_EPOCH_NS for d in truth] == [0, 10_000_000]
    assert truth[1]["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 0.5}
    q = truth[1]["pose"]["orientation"]
    assert [q[k] for k in "xyzw"] == pytest.approx([0.0, 0.0, 0.7071067812, 0.7071067812])


@pytest.mark.parametrize(("name", "text", "message"), [
    ("uwb.txt", INROL_FILES["uwb.txt"].replace(" 3.0\n", " 3.o\n"),
     "uwb.txt: line 3: r: not a number: '3.o'"),
    ("imu.txt", INROL_FILES["imu.txt"].replace(" 0.03 0.1 0.2 9.8\n2", " 0.03 0.1 0.2\n2", 1),
     "imu.txt: line 3: expected 8 values, got 7"),
    ("uwb.txt", INROL_FILES["uwb.txt"].replace("0.110000000000 3", "0.11s 3"),
     "uwb.txt: line 4: timestamp: not a number: '0.11s'"),
    ("imu_pose.txt", "", "imu_pose.txt: No such file or directory"),
])
def test_import_inrol_errors_are_one_line(tmp_path: Path, name: str, text: str,
                                          message: str) -> None:
    bad = uwbd("import", "inrol", str(inrol_dir(tmp_path / "run", **{name: text})),
               cwd=tmp_path)
    assert bad.returncode == 2
    (line,) = bad.stderr.splitlines()
    assert line.startswith("uwbd import: ") and str(tmp_path / "run" / name) in line
    assert message in line and "Traceback" not in bad.stderr
    assert not (tmp_path / "import.mcap").exists()


@pytest.mark.skipif(not INROL.is_dir(), reason="shared/data not beside the repository")
def test_import_real_inrol_run(tmp_path: Path) -> None:
    imp = uwbd("import", "inrol", str(INROL), "-o", "r.mcap", cwd=tmp_path)
    assert imp.returncode == 0, imp.stderr
    rows = {name: [line.split() for line in (INROL / name).read_text().splitlines()[1:]]
            for name in ("imu.txt", "uwb.txt", "imu_pose.txt")}
    contents = read_log(tmp_path / "r.mcap")
    rec = load_recording(contents, "r.mcap")
    imu = [f for f in rec.frames if isinstance(f, ImuSample)]
    uwb = [f for f in rec.frames if isinstance(f, UwbRanges)]
    assert len(imu) == len(rows["imu.txt"])
    assert sum(len(m.ranges) for m in uwb) == len(rows["uwb.txt"])
    assert len(uwb) == len({r[1] for r in rows["uwb.txt"]})
    assert len(rec.truth_t_ns) == len(rows["imu_pose.txt"])
    assert set(rec.config.anchors_m) == set(range(1, 9))
    # the anchors' antenna orientations (x, y, z, w): kept in the config's table form
    first = (INROL / "anchor.txt").read_text().splitlines()[1].split()
    axes = np.array(rec.config.anchor_axes[int(first[0])])
    x, y, z, w = (float(v) for v in first[4:8])
    assert axes == pytest.approx(quat_to_matrix(np.array([w, x, y, z])), abs=1e-9)
    assert set(rec.config.anchor_axes) == set(range(1, 9))
    assert rec.frames[0].t_ns - INROL_EPOCH_NS < 100_000_000  # the files' clock starts at 0


def test_json_never_carries_nan() -> None:
    assert json.loads(strict_json({"a": math.nan, "b": [1.0, math.inf], "c": {"d": -math.inf}})) \
        == {"a": None, "b": [1.0, None], "c": {"d": None}}
    assert b"NaN" not in strict_json({"x": [math.nan] * 3})


def test_chunks_and_their_indexes_point_at_the_right_records(tmp_path: Path) -> None:
    """uwbd's own chunk writer (uwbd.logs.chunked) against the MCAP spec: the library's
    seeking reader finds every message through the summary, each chunk index gives its
    chunk's time span, and every message index entry points at a message record of its
    channel with its log time inside the decompressed chunk."""
    path = tmp_path / "x.mcap"
    with LogWriter(path, chunk_bytes=2000) as w:  # small chunks: many of them
        for i in range(500):
            w.json(f"/t{i % 3}", 1000 + (i * 37) % 5000, {"i": i})  # out of time order
    data = path.read_bytes()
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert sum(1 for _ in reader.iter_messages()) == 500
    assert summary.statistics.message_count == 500
    assert dict(summary.statistics.channel_message_counts) == {1: 167, 2: 167, 3: 166}
    assert (summary.statistics.message_start_time, summary.statistics.message_end_time) \
        == (1000, 5995)
    assert len(summary.chunk_indexes) > 5
    checked = 0
    for ci in summary.chunk_indexes:
        at = ci.chunk_start_offset + 9  # opcode, record length
        start, end, size, _crc = struct.unpack_from("<QQQI", data, at)
        at += 28 + 4 + struct.unpack_from("<I", data, at + 28)[0]  # compression name
        length = struct.unpack_from("<Q", data, at)[0]
        records = zstandard.decompress(data[at + 8:at + 8 + length], max_output_size=size)
        assert (start, end) == (ci.message_start_time, ci.message_end_time)
        times = []
        for channel, offset in ci.message_index_offsets.items():
            body_len = struct.unpack_from("<Q", data, offset + 1)[0]
            ch, n = struct.unpack_from("<HI", data, offset + 9)
            assert data[offset] == 0x07 and ch == channel and 6 + n == body_len
            for k in range(n // 16):
                t, o = struct.unpack_from("<QQ", data, offset + 15 + 16 * k)
                op, _, mch, _, log_t, pub_t = struct.unpack_from("<BQHIQQ", records, o)
                assert (op, mch, log_t, pub_t) == (0x05, channel, t, t)
                times.append(t)
                checked += 1
        assert (min(times), max(times)) == (start, end)
    assert checked == 500


def test_two_writers_in_one_folder_in_the_same_second_keep_both_logs(tmp_path: Path) -> None:
    """Two daemons of one robot name logging into one folder, started in the same second:
    each gets a file of its own, also when the other made the name it chose between its
    check and its open (the file is created exclusively); neither replaces the other's."""
    config = parse("")
    first = McapSink(config, directory=tmp_path)
    first.raw("imu", EPOCH_NS, b"\x55\x51" + bytes(9))
    first.close()
    (taken,) = first.files

    class Raced(McapSink):  # its first name check ran before the other made the file
        calls = 0

        def _next_name(self, t_ns: int) -> Path:
            self.calls += 1
            return taken if self.calls == 1 else super()._next_name(t_ns)

    second = Raced(config, directory=tmp_path)
    second.raw("imu", EPOCH_NS + 1, b"\x55\x51" + bytes(10))
    second.close()
    assert not second.error and len(second.files) == 1 and second.files[0] != taken
    assert [len(read_log(f).messages) for f in (taken, second.files[0])] == [1, 1]
    assert read_log(taken).messages[0].data.endswith(bytes(9)) \
        and not read_log(taken).messages[0].data.endswith(bytes(10))


def test_a_record_out_of_range_is_refused_and_the_file_stays_whole(tmp_path: Path) -> None:
    """A time MCAP cannot hold (negative) is refused before it touches the chunk: the
    records around it, the indexes and the summary stay right."""
    path = tmp_path / "x.mcap"
    with LogWriter(path) as w:
        w.json("/a", 1000, {"i": 0})
        with pytest.raises(UNENCODABLE):
            w.json("/a", -5, {"i": 1})
        w.json("/b", 2000, {"i": 2})
        w.flush()
        w.json("/a", 3000, {"i": 3})
    with path.open("rb") as f:
        reader = make_reader(f)
        got = [(c.topic, m.log_time) for _, c, m in reader.iter_messages()]
    assert got == [("/a", 1000), ("/b", 2000), ("/a", 3000)]
    assert [m.log_time_ns for m in read_log(path).messages] == [1000, 2000, 3000]


def _library_read(path: Path) -> tuple[list[tuple[str, int, bytes]], dict[str, str]]:
    contents = reading._read_by_library(path, path.read_bytes(), intact.Damage())
    return [tuple(m) for m in contents.messages], contents.metadata  # type: ignore[misc]


def test_the_lean_scan_reads_what_the_library_reads(tmp_path: Path) -> None:
    """Every record of whole logs (a simulated one, and a replay's output with every
    channel, written by uwbd's chunk writer and by the library's writer) comes out of the
    lean scan exactly as the library's reader gives it, raw bytes of every length among
    them (a protobuf length of two bytes too)."""
    sim = simulate(SimConfig(segments=SHORT, seed=3))
    source = tmp_path / "sim.mcap"
    write_simulation(sim, source)
    replayed = tmp_path / "replayed.mcap"
    assert uwbd("replay", str(source), "-o", str(replayed)).returncode == 0
    long_raw = tmp_path / "long.mcap"
    with LogWriter(long_raw, sources=(SourceInfo("uwb", "nlink"),), chunk_bytes=4096) as log:
        for k in range(300):
            log.raw("uwb", k, bytes([k % 251]) * (k + k // 2))  # 0 to 448 bytes
    recovered = tmp_path / "recovered.mcap"  # the mcap library's own writer
    assert uwbd("recover", str(replayed), "-o", str(recovered)).returncode == 0
    for path in (source, replayed, long_raw, recovered):
        whole = reading._read_whole(path.read_bytes())
        messages, metadata = _library_read(path)
        assert [tuple(m) for m in whole.messages] == messages, path
        assert whole.metadata == metadata and metadata["config_toml"] is not None
        assert not whole.truncated
    assert {len(m.data) for m in read_log(long_raw).messages} >= {0, 1, 127, 129, 448}


@pytest.mark.skipif(scan.C_SCAN is None, reason="the log reader's C loops are not built")
def test_the_scans_loops_in_c_read_what_their_reference_reads(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``uwbd/logs/_scan.c`` (a chunk's run of messages; each as a LogMessage) against the
    Python loops it translates: raw reads of every length (a two-byte protobuf length
    among them, decoded by the reference's own function), JSON records, an unknown
    channel, and a chunk cut inside a message, which both refuse alike."""
    path = tmp_path / "a.mcap"
    with LogWriter(path, sources=(SourceInfo("uwb", "nlink"),), chunk_bytes=2048) as log:
        for k in range(300):
            log.raw("uwb", k, bytes([k % 251]) * (k + k // 2))
            log.json("/truth", k, {"k": k})
    buf = path.read_bytes()
    in_c = reading._read_whole(buf)
    with monkeypatch.context() as m:
        m.setattr(scan, "C_SCAN", None)
        m.setattr(reading, "C_SCAN", None)
        reference = reading._read_whole(buf)
    assert [tuple(x) for x in in_c.messages] == [tuple(x) for x in reference.messages]
    assert in_c.metadata == reference.metadata and len(in_c.messages) == 600
    assert {len(x.data) for x in in_c.messages if x.topic == "/raw/uwb"} >= {0, 127, 129, 448}
    assert scan.C_SCAN is not None
    message = struct.pack("<BQHIQQ", 0x05, 22 + 3, 1, 0, 7, 7) + b"abc"
    channel = struct.pack("<BQ", 0x04, 0)  # another record: the run stops at it
    assert scan.C_SCAN.chunk_messages(message + channel, 0) == ([(1, 7, b"abc")], 34)
    for cut, why in ((len(message) - 1, "ends mid-record"), (5, "ends mid-record")):
        with pytest.raises(ValueError, match=why):
            scan.C_SCAN.chunk_messages(message[:cut], 0)
    short = struct.pack("<BQ", 0x05, 10) + bytes(10)
    with pytest.raises(ValueError, match="message length"):
        scan.C_SCAN.chunk_messages(short, 0)
    records = [(9, 1, b"\x0a\x02hi"), (9, 2, b"\x0a"), (3, 3, b"x")]
    out: list[reading.LogMessage] = []
    scan.C_SCAN.log_messages(records, {9: "/raw/a"}, {9}, fx.decode_raw, reading.LogMessage,
                             out)
    assert out == [("/raw/a", 1, b"hi"), ("/raw/a", 2, b"\x0a"), ("?", 3, b"x")]
    assert all(type(x) is reading.LogMessage for x in out)


@settings(max_examples=40, deadline=None)
@given(cut=st.floats(0.0, 1.0), flips=st.lists(st.tuples(st.floats(0.0, 1.0),
                                                        st.integers(1, 255)), max_size=3))
@example(cut=1.0, flips=[(0.625, 128)])  # a chunk's size field: OverflowError, MemoryError
@example(cut=0.5, flips=[(0.015625, 1)])  # the first chunk, which defined every channel
def test_a_damaged_or_cut_log_reads_as_the_library_reads_it(
        tmp_path_factory: pytest.TempPathFactory, cut: float,
        flips: list[tuple[float, int]]) -> None:
    """A file cut anywhere or with bytes flipped anywhere: ``read_log`` never raises; what
    the lean scan accepts, the library reads the same; what it does not, the library reads
    (and says where the file is damaged)."""
    tmp = tmp_path_factory.mktemp("damaged")
    path = tmp / "a.mcap"
    with LogWriter(path, sources=(SourceInfo("uwb", "nlink"),), chunk_bytes=512) as log:
        for k in range(200):
            log.raw("uwb", k * 10**7, bytes((k % 7,)) * (k % 40))
            log.json("/truth", k * 10**7, {"k": k})
    data = bytearray(path.read_bytes())
    for where, xor in flips:
        data[min(int(where * len(data)), len(data) - 1)] ^= xor
    damaged = tmp / "damaged.mcap"
    damaged.write_bytes(bytes(data[: max(8, int(cut * len(data)))]))
    contents = read_log(damaged)
    messages, _ = _library_read(damaged)
    if not contents.truncated:
        assert contents.error == ""
        # the scan ignores the summary section, which the library reads (and may find damaged)
        assert [tuple(m) for m in contents.messages] == messages[: len(contents.messages)]
    else:
        assert str(damaged) in contents.error
        # the library stops at the first damage; read_log goes on from the next intact chunk
        assert [tuple(m) for m in contents.messages][: len(messages)] == messages
        original = [tuple(m) for m in read_log(path).messages]
        got = iter(original)
        assert all(any(m == o for o in got) for m in map(tuple, contents.messages))


def _simulated_log(tmp_path: Path, seed: int
                   ) -> tuple[Path, bytes, list[tuple[object, ...]], list[tuple[int, int]]]:
    """A short simulated log: its path, bytes, messages, and its chunks (offset, length)."""
    path = tmp_path / "sim.mcap"
    write_simulation(simulate(SimConfig(segments=SHORT, seed=seed)), path)
    with path.open("rb") as f:
        chunks = [(c.chunk_start_offset, c.chunk_length)
                  for c in make_reader(f).get_summary().chunk_indexes]
    return path, path.read_bytes(), [tuple(m) for m in read_log(path).messages], chunks


def test_one_damaged_chunk_costs_that_chunk_only(tmp_path: Path) -> None:
    """A bit flipped in each chunk of a real log in turn: every other chunk's messages are
    read back (read_log, so replay, report, export, survey; and recover), and the warning
    says what was skipped."""
    _, buf, whole, chunks = _simulated_log(tmp_path, 5)
    assert len(chunks) >= 5
    # the messages each chunk holds: a run of the file's, in order
    counts = [sum(isinstance(r, Message) for r in intact.intact_records(
        buf[:8] + buf[start:start + length], intact.Damage())) for start, length in chunks]
    assert sum(counts) == len(whole)
    for k, (start, length) in enumerate(chunks):
        first = sum(counts[:k])
        damaged = bytearray(buf)
        damaged[start + length // 2] ^= 0x10
        bad = tmp_path / f"bad{k}.mcap"
        bad.write_bytes(bytes(damaged))
        contents = read_log(bad)
        assert contents.truncated and "1 damaged stretch(es) skipped" in contents.error
        assert [tuple(m) for m in contents.messages] == (
            whole[:first] + whole[first + counts[k]:]), k
    for k in (0, 2):  # the first chunk held the channels: recover finds them in the summary
        fixed = tmp_path / f"fixed{k}.mcap"
        done = uwbd("recover", str(tmp_path / f"bad{k}.mcap"), "-o", str(fixed))
        assert done.returncode == 0, done.stderr
        assert "damaged stretch(es) skipped" in done.stdout
        assert ([tuple(m) for m in read_log(fixed).messages]
                == [tuple(m) for m in read_log(tmp_path / f"bad{k}.mcap").messages]), k


def test_a_damaged_chunk_length_field_costs_nothing(tmp_path: Path) -> None:
    """#44: each bit of a chunk's record-length field flipped in turn (the first chunk's, a
    middle one's, the last one's): every message is read back, by the chunk's own fields,
    and the warning says the length field was damaged."""
    _, buf, whole, chunks = _simulated_log(tmp_path, 6)
    starts = [start for start, _ in chunks]
    bad = tmp_path / "bad.mcap"
    for start in (starts[0], starts[len(starts) // 2], starts[-1]):
        for bit in range(64):
            damaged = bytearray(buf)
            damaged[start + 1 + bit // 8] ^= 1 << (bit % 8)
            bad.write_bytes(bytes(damaged))
            contents = read_log(bad)
            assert [tuple(m) for m in contents.messages] == whole, (start, bit)
            assert "length field is damaged" in contents.error, (start, bit)
    done = uwbd("recover", str(bad), "-o", str(tmp_path / "fixed.mcap"))
    assert done.returncode == 0 and f"{len(whole)} messages recovered" in done.stdout


def _crashed_log(tmp_path: Path) -> tuple[Path, int, list[tuple[object, ...]]]:
    """A simulated log as a crash leaves it: every chunk whole, no summary, no footer."""
    path = tmp_path / "sim.mcap"
    write_simulation(simulate(SimConfig(segments=SHORT, seed=7)), path)
    with path.open("rb") as f:
        last = max(c.chunk_start_offset + c.chunk_length
                   for c in make_reader(f).get_summary().chunk_indexes)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:last])
    return cut, last, [tuple(m) for m in read_log(cut).messages]


def test_a_zeroed_tail_costs_nothing_and_is_never_read(tmp_path: Path) -> None:
    """#44: what a power loss leaves, a file whose last 3 GB are zeros (sparse here, so the
    test costs no disk): read up to the zeros, found by walking the records' headers and a
    bounded read at each end, never reading the tail; replay and recover say so."""
    cut, last, messages = _crashed_log(tmp_path)
    tailed = tmp_path / "tailed.mcap"
    tailed.write_bytes(cut.read_bytes())
    with tailed.open("r+b") as f:
        f.truncate(last + 3 * 2**30)
    damage = intact.Damage()
    with tailed.open("rb") as f:
        assert intact.intact_size(f, damage) == last
    assert damage.zeroed == (last, last + 3 * 2**30)
    contents = read_log(tailed)
    assert [tuple(m) for m in contents.messages] == messages
    assert f"bytes {last}-{last + 3 * 2**30} are zeros" in contents.error
    assert "without a footer" in contents.error and "mid-record" not in contents.error
    replayed = uwbd("replay", str(tailed))
    assert replayed.returncode == 0 and "are zeros" in replayed.stderr, replayed.stderr
    done = uwbd("recover", str(tailed), "-o", str(tmp_path / "fixed.mcap"))
    assert done.returncode == 0 and f"{len(messages)} messages recovered" in done.stdout
    assert (tmp_path / "fixed.mcap").stat().st_size < last * 2


def test_a_zeroed_tail_after_a_damaged_record_is_found_from_the_end(tmp_path: Path) -> None:
    """A torn record before the zeros (its header claims more than the file holds): the
    headers stop short of the tail, which is then found from the file's end."""
    cut, last, messages = _crashed_log(tmp_path)
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(cut.read_bytes() + struct.pack("<BQ", 0x06, 2**40) + b"\x01" * 100
                     + bytes(2**20))
    contents = read_log(torn)
    assert [tuple(m) for m in contents.messages] == messages
    assert f"bytes {last + 109}-{last + 109 + 2**20} are zeros" in contents.error


def test_recover_of_random_bytes_writes_nothing_and_fails(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + os.urandom(5000))
    done = uwbd("recover", str(junk), "-o", str(tmp_path / "out.mcap"))
    assert done.returncode == 1 and "no message could be recovered" in done.stderr
    assert not (tmp_path / "out.mcap").exists()


@given(st.builds(ImuSample, st.integers(0, 2**62), st.tuples(*[st.floats()] * 3),
                 st.tuples(*[st.floats()] * 3), st.none() | st.floats(),
                 st.none() | st.tuples(*[st.floats(-180, 180)] * 3),
                 st.none() | st.tuples(*[st.integers(-2**15, 2**15)] * 3),
                 st.none() | st.tuples(*[st.floats(-1, 1)] * 4),
                 st.none() | st.integers(0, 2**62)))
def test_an_imu_record_holds_its_fields_in_order_whichever_are_set(sample: ImuSample) -> None:
    """The common record (accelerometer, gyro, perhaps the temperature) has a path of its
    own: the same bytes as every other (NaN as null, a field without a value left out)."""
    expected: dict[str, object] = {"type": "ImuSample", "timestamp": {
        "sec": sample.t_ns // 10**9, "nsec": sample.t_ns % 10**9}}
    for name in ("t_ns", "acc_mps2", "gyro_rps", "temperature_c", "angle_deg", "mag_raw",
                 "quaternion_wire", "device_time_ns"):
        if getattr(sample, name) is not None:
            expected[name] = getattr(sample, name)
    assert frame_to_json(sample) == strict_json(expected)
