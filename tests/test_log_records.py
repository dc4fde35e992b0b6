"""The output log's common IMU read in C (``uwbd/logs/_records.c``) against its reference,
``LogWriter.read`` through ``raw`` and ``frame``: real MCAP files, byte for byte."""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from drivers.frames import AnchorRange, Frame, ImuSample, UwbRanges
from drivers.wit import encode as encode_wit
from uwbd.config import parse
from uwbd.logs import mcaplog
from uwbd.logs.mcaplog import LogWriter
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.tools.simulator import EPOCH_NS, SimConfig, simulate

needs_c = pytest.mark.skipif(mcaplog.C_RECORDS is None, reason="the log's C writer is not built")


class Counted:
    """The C writer, its answers kept."""

    def __init__(self) -> None:
        self.answers: list[int] = []

    def imu_read(self, *args: Any) -> int:
        assert mcaplog.C_RECORDS is not None
        answer = mcaplog.C_RECORDS.imu_read(*args)
        self.answers.append(answer)
        return answer


def odd_reads() -> list[tuple[str, int, bytes, Frame]]:
    """Two seconds of a simulated IMU's reads, and among them every kind of read the C
    writer must decline or split: samples with more than accel, gyro and temperature, a
    number not finite, ints or lists for floats, no temperature, a temperature that is an
    int, reads of no bytes and of more than 127 (a two-byte length), a time past 2**63,
    a UWB epoch with an anchor's position (the anchors' scene comes first)."""
    sim = simulate(SimConfig(seed=3, segments=((1.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.3, 0.0))))
    out: list[tuple[str, int, bytes, Frame]] = []
    for k, s in enumerate(sim.imu):
        odd: Any = {
            7: {"angle_deg": (1.0, 2.0, 3.0)}, 11: {"mag_raw": (1, 2, 3)},
            13: {"quaternion_wire": (1.0, 0.0, 0.0, 0.0)}, 17: {"device_time_ns": 5},
            19: {"acc_mps2": (math.nan, 0.0, 9.8)}, 23: {"gyro_rps": (0.0, math.inf, 0.0)},
            29: {"acc_mps2": (0, 0, 9)}, 31: {"gyro_rps": [0.0, 0.0, 0.0]},
            37: {"temperature_c": None}, 41: {"temperature_c": 25},
            43: {"temperature_c": math.nan}, 47: {"t_ns": 2**63 + 5},
            53: {"acc_mps2": (1e-5, -1.5e-6, 1e16)},
        }.get(k % 60, {})
        fields = {name: getattr(s, name) for name in ImuSample.__slots__}  # type: ignore[attr-defined]
        sample = ImuSample(**{**fields, **odd})
        data = encode_wit(s)
        if k % 50 == 3:
            data = b""
        elif k % 50 == 9:
            data = data * 8  # 176 bytes
        out.append(("imu", s.t_ns + 1_000, data, sample))
        if k % 40 == 0:
            anchor = AnchorRange(100 + k // 40, 4.0, 90.0, (float(k), 1.0, 2.0))
            epoch = UwbRanges(s.t_ns, (anchor,))
            out.append(("uwb", s.t_ns + 2_000, b"\x55" * 20, epoch))
    return out


def write(path: Path, reads: list[tuple[str, int, bytes, Frame]], c_records: Any,
          chunk_bytes: int) -> None:
    with LogWriter(path, chunk_bytes=chunk_bytes) as log:
        log._c_records = c_records
        for source, t_ns, data, frame in reads:
            log.read(source, t_ns, data, frame)


@needs_c
@pytest.mark.parametrize("chunk_bytes", [700, 64 * 1024])
def test_the_c_writer_writes_the_references_bytes(tmp_path: Path, chunk_bytes: int) -> None:
    """The same reads through the C writer and through the reference make the same file,
    byte for byte; the C writer took the common reads, declined the others, and ended its
    chunk after either record (small chunks: every branch)."""
    reads = odd_reads()
    counted = Counted()
    write(tmp_path / "c.mcap", reads, counted, chunk_bytes)
    write(tmp_path / "py.mcap", reads, None, chunk_bytes)
    assert (tmp_path / "c.mcap").read_bytes() == (tmp_path / "py.mcap").read_bytes()
    answers = counted.answers
    imu_reads = sum(source == "imu" for source, *_ in reads)
    assert answers.count(0) >= 12 * imu_reads // 60  # the odd ones, declined
    assert len(answers) - answers.count(0) > imu_reads // 3  # the common ones, written
    if chunk_bytes < 1000:
        assert 1 in answers and 3 in answers
    with (tmp_path / "c.mcap").open("rb") as f:  # the library's reader agrees
        topics = [c.topic for _, c, _ in make_reader(f).iter_messages(log_time_order=False)]
    assert topics.count("/raw/imu") == imu_reads and topics.count("/imu") == imu_reads
    assert topics.count("/anchors") == sum(source == "uwb" for source, *_ in reads)


@needs_c
def test_the_c_writers_json_is_orjsons_for_awkward_numbers(tmp_path: Path) -> None:
    """Numbers orjson writes in its own way (1e-05 as 0.00001, 1e-06 as 1e-6, 1e16 as
    1e+16, whole floats with .0) come out as the reference writes them, and read back."""
    samples = [ImuSample(EPOCH_NS + k, (1e-5, -1.5e-6, 1e16), (25.0, -0.0, 5e-324), 1e-7)
               for k in range(3)]
    reads = [("imu", s.t_ns, b"\x55\x51" + bytes(9), s) for s in samples]
    counted = Counted()
    write(tmp_path / "c.mcap", reads, counted, 64 * 1024)
    write(tmp_path / "py.mcap", reads, None, 64 * 1024)
    assert counted.answers == [2, 2]  # (the first read registers the channels)
    assert (tmp_path / "c.mcap").read_bytes() == (tmp_path / "py.mcap").read_bytes()
    imu = [m for m in read_log(tmp_path / "c.mcap").messages if m.topic == "/imu"]
    assert b'"acc_mps2":[0.00001,-1.5e-6,1e+16],"gyro_rps":[25.0,-0.0,5e-324]' in imu[1].data


def test_a_read_whose_time_the_log_cannot_hold_keeps_its_frame(tmp_path: Path) -> None:
    """A /raw record refused (a negative receive time) still lets its frame's record in,
    as two separate calls did; the refusal reaches the caller (the sink counts it)."""
    path = tmp_path / "x.mcap"
    sample = ImuSample(EPOCH_NS, (0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 25.0)
    with LogWriter(path) as log:
        log.read("imu", EPOCH_NS, b"\x55" * 11, sample)
        with pytest.raises(struct.error):
            log.read("imu", -1, b"\x55" * 11, sample)
    assert [m.topic for m in read_log(path).messages] == ["/raw/imu", "/imu", "/imu"]


def test_a_read_whose_records_the_log_cannot_hold_counts_each(tmp_path: Path) -> None:
    sample = ImuSample(EPOCH_NS, (0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 25.0)
    log = McapSink(parse(""), path=tmp_path / "x.mcap")
    for t_ns, frame in ((EPOCH_NS, sample), (-1, dataclasses.replace(sample, t_ns=-2)),
                        (-1, sample)):  # both, neither, its frame only
        log.raw("imu", t_ns, b"\x55" * 11)
        log.frame(frame)
    log.close()
    assert log.bad_records == 3
    assert [m.topic for m in read_log(tmp_path / "x.mcap").messages
            if m.topic.startswith(("/raw", "/imu"))] == ["/raw/imu", "/imu", "/imu"]


def _writer(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    if name == "reference":
        monkeypatch.setattr(mcaplog, "C_RECORDS", None)
    elif mcaplog.C_RECORDS is None:
        pytest.skip("the log's C writer is not built")


@pytest.mark.parametrize("writer", ["C", "reference"])
def test_a_full_disk_counts_both_records_of_a_read(small_disk: Path, writer: str,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """On a disk that fills, every record of the IMU reads (two a read) is in a finished
    file or counted lost, with either writer."""
    _writer(writer, monkeypatch)
    (small_disk / "filler").write_bytes(b"\0" * 150_000)
    log = McapSink(parse(""), directory=small_disk)
    t_ns, written = EPOCH_NS, 0
    for k in range(6000):  # 30 s at 200 Hz
        if k == 4000:
            (small_disk / "filler").unlink()  # room again
        noise = os.urandom(6) if k < 4000 else bytes(6)  # incompressible until then
        sample = ImuSample(t_ns, tuple(b / 7.0 for b in noise[:3]),  # type: ignore[arg-type]
                           tuple(b / 9.0 for b in noise[3:]), 25.0)
        log.raw("imu", t_ns + 1000, os.urandom(22) if k < 4000 else bytes(22))
        log.frame(sample)
        written += 2
        t_ns += 5_000_000
    log.close()
    kept = 0
    for path in log.files:
        contents = read_log(path)
        assert not contents.truncated, contents.error
        kept += sum(m.topic in ("/raw/imu", "/imu") for m in contents.messages)
    assert log.records_lost > 0 and kept + log.records_lost == written


@pytest.mark.parametrize("writer", ["C", "reference"])
def test_a_raw_record_that_fails_to_reach_the_disk_counts_its_frame(
        small_disk: Path, writer: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every /raw record fills its chunk (bigger than the chunk size): when the disk is full,
    ending that chunk fails before the frame's record is written, and the frame is counted
    among the records the cut loses (``unflushed``: two for every read since the flush)."""
    _writer(writer, monkeypatch)
    sample = ImuSample(EPOCH_NS, (0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 25.0)
    log = LogWriter(small_disk / "x.mcap", chunk_bytes=700)
    reads = 0
    with pytest.raises(OSError):  # the disk fills somewhere in the loop
        for k in range(1000):
            reads += 1
            log.read("imu", EPOCH_NS + k, os.urandom(1000), sample)
    assert log.unflushed == 2 * reads
    log.abandon()
