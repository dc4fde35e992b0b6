"""The output log's records: the open chunk in C (``uwbd/logs/_chunk.c``) against its
reference ``chunked.PyChunk`` (real MCAP files, byte for byte), and what a record the log
cannot hold, or a full disk, costs."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from drivers.frames import AnchorRange, Frame, ImuSample, UwbRanges
from drivers.wit import encode as encode_wit
from uwbd.config import parse
from uwbd.fusion.core import native
from uwbd.logs.chunked import PyChunk, new_chunk
from uwbd.logs.mcaplog import UNENCODABLE, LogWriter
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.tools.simulator import EPOCH_NS, SimConfig, simulate

needs_c = pytest.mark.skipif(isinstance(new_chunk(), PyChunk),
                             reason="the log's C chunk is not built")


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


def write(path: Path, reads: list[tuple[str, int, bytes, Frame]], chunk_bytes: int) -> None:
    with LogWriter(path, chunk_bytes=chunk_bytes) as log:
        for source, t_ns, data, frame in reads:
            log.raw(source, t_ns, data)
            log.frame(frame)


@needs_c
@pytest.mark.parametrize("chunk_bytes", [700, 64 * 1024])
def test_the_c_chunk_writes_the_references_bytes(tmp_path: Path, chunk_bytes: int) -> None:
    """The same records (every kind of frame, reads of no bytes and of 176, anchors' scenes,
    schemas and channels mid-chunk) through the C chunk and through the reference make the
    same file, byte for byte, which the library's reader reads (small chunks: one ends after
    nearly every record)."""
    reads = [r for r in odd_reads() if r[1] < 2**63]
    write(tmp_path / "c.mcap", reads, chunk_bytes)
    with native.pure_python():
        write(tmp_path / "py.mcap", reads, chunk_bytes)
    assert (tmp_path / "c.mcap").read_bytes() == (tmp_path / "py.mcap").read_bytes()
    with (tmp_path / "c.mcap").open("rb") as f:  # the library's reader agrees
        topics = [c.topic for _, c, _ in make_reader(f).iter_messages(log_time_order=False)]
    imu_reads = sum(source == "imu" for source, *_ in reads)
    assert topics.count("/raw/imu") == imu_reads and topics.count("/imu") == imu_reads
    assert topics.count("/anchors") == sum(source == "uwb" for source, *_ in reads)


@pytest.mark.parametrize("pure", [False, True], ids=["C", "reference"])
def test_a_record_whose_time_the_log_cannot_hold_changes_nothing(tmp_path: Path,
                                                                 pure: bool) -> None:
    """A /raw record refused (a negative receive time, one past 2**64) raises what the sink
    counts and leaves the chunk as it was: the records after it are whole."""
    path = tmp_path / "x.mcap"
    sample = ImuSample(EPOCH_NS, (0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 25.0)
    with native.pure_python() if pure else contextlib.nullcontext(), LogWriter(path) as log:
        log.raw("imu", EPOCH_NS, b"\x55" * 11)
        for bad in (-1, 2**64):
            with pytest.raises(UNENCODABLE):
                log.raw("imu", bad, b"\x55" * 11)
        log.frame(sample)
    assert [m.topic for m in read_log(path).messages] == ["/raw/imu", "/imu"]


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


@pytest.mark.parametrize("pure", [False, True], ids=["C", "reference"])
def test_a_full_disk_counts_both_records_of_a_read(small_disk: Path, pure: bool) -> None:
    """On a disk that fills, every record of the IMU reads (two a read) is in a finished
    file or counted lost, with either chunk."""
    with native.pure_python() if pure else contextlib.nullcontext():
        _fill_the_disk(small_disk)


def _fill_the_disk(small_disk: Path) -> None:
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
