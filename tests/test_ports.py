"""The C reader's thread (uwbd/service/_reader.c) on real pseudo-terminals: every byte in
order, stamped on the epoch clock, the event loop woken only when a read matters, a lost
port said once and no port read after it is removed. (The daemon with it, and with the
event loop reading instead, is tests/test_daemon.py's.)"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import pty
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType

import pytest

from uwbd.config import parse
from uwbd.service.pipeline import Pipeline
from uwbd.service.ports import EpochClock, ReadQueue, SerialSource
from uwbd.service.reads import ThreadReads, _reader_module

READER = _reader_module()
pytestmark = pytest.mark.skipif(READER is None, reason="the C reader is not built or ruled out")
HOLD_NS = 100_000_000


@pytest.fixture
def reader() -> Iterator[tuple[ModuleType, object]]:
    assert READER is not None
    r = READER.Reader(time.time_ns() - time.monotonic_ns(), HOLD_NS)
    yield READER, r
    r.close()


@pytest.fixture
def port() -> Iterator[Callable[[], tuple[int, int]]]:
    """Makes ptys (device side, daemon side): raw, the daemon's side non-blocking, as
    pyserial opens a port; all closed at the end."""
    fds: list[int] = []

    def make() -> tuple[int, int]:
        device, ours = pty.openpty()
        tty.setraw(ours)
        os.set_blocking(ours, False)
        fds.extend((device, ours))
        return device, ours
    yield make
    for fd in fds:
        with contextlib.suppress(OSError):  # a test closed it already
            os.close(fd)


def wait_wake(r: object, timeout_s: float = 2.0) -> bool:
    return bool(select.select([r.wake_fd], [], [], timeout_s)[0])  # type: ignore[attr-defined]


def send(device: int, frames: int, period_s: float = 0.005) -> threading.Thread:
    """``frames`` 22-byte frames, numbered, one each ``period_s`` (a 200 Hz IMU)."""
    def write() -> None:
        t = time.monotonic()
        for k in range(frames):
            os.write(device, bytes([k % 256]) * 22)
            t += period_s
            time.sleep(max(0.0, t - time.monotonic()))
    thread = threading.Thread(target=write)
    thread.start()
    return thread


def test_imu_reads_wait_for_the_pose_and_arrive_whole_in_order(reader, port) -> None:
    _, r = reader
    device, ours = port()
    r.add(ours, 3, False)
    before = time.time_ns()
    due = before + 20_000_000
    r.set_due(due)
    writer = send(device, 200)
    wakes, reads = 0, []
    while True:
        if not wait_wake(r, 0.3):
            if writer.is_alive():
                continue
            break
        wakes += 1
        got = r.drain()
        reads += got
        if got and got[-1][1] >= due:  # a pose went out: the next is due 20 ms on
            due = got[-1][1] + 20_000_000
        r.set_due(due)
    writer.join()
    reads += r.drain()
    after = time.time_ns()
    data = b"".join(d for _, _, d, _ in reads)
    assert data == b"".join(bytes([k]) * 22 for k in range(200))  # every byte, in order
    assert {s for s, _, _, _ in reads} == {3} and {e for _, _, _, e in reads} == {0}
    times = [t for _, t, _, _ in reads]
    assert times == sorted(times) and before <= times[0] and times[-1] <= after
    # ~1 s of reads at 200 Hz woke the loop about as often as poses are due (50 Hz), not
    # once a read
    assert wakes < len(reads) / 2, (wakes, len(reads))


def test_an_urgent_port_wakes_at_once(reader, port) -> None:
    _, r = reader
    device, ours = port()
    r.add(ours, 1, True)
    r.set_due(2**63 - 1)  # no pose due: only urgency wakes
    os.write(device, b"range")
    assert wait_wake(r)
    ((source, _, data, error),) = r.drain()
    assert (source, data, error) == (1, b"range", 0)


def test_held_reads_wake_the_loop_after_max_hold(reader, port) -> None:
    _, r = reader
    device, ours = port()
    r.add(ours, 0, False)
    r.set_due(2**63 - 1)
    written = time.monotonic()
    os.write(device, b"x" * 22)
    time.sleep(0.02)
    woken = select.select([r.wake_fd], [], [], 0)[0]
    if time.monotonic() - written < 0.08:  # (a machine this busy proves nothing here)
        assert not woken  # held, not due
    assert wait_wake(r, 1.0)  # held HOLD_NS: the loop takes it
    assert [d for _, _, d, _ in r.drain()] == [b"x" * 22]


def test_a_lost_port_is_said_once_and_read_no_more(reader, port) -> None:
    _, r = reader
    device, ours = port()
    r.add(ours, 5, False)
    os.write(device, b"last words")
    time.sleep(0.05)
    os.close(device)  # the device goes: our side of the pty reads end of file (or EIO)
    assert wait_wake(r)
    time.sleep(0.05)
    reads = r.drain()
    assert reads[-1][0] == 5 and reads[-1][2] is None and reads[-1][3] in (0, errno.EIO)
    assert b"".join(d for _, _, d, _ in reads[:-1]) == b"last words"
    assert r.drain() == []  # said once
    r.remove(ours)  # the thread dropped it already: no error


def test_a_removed_port_is_not_read_and_the_fd_can_be_reused(reader, port) -> None:
    _, r = reader
    device, ours = port()
    r.add(ours, 2, True)
    r.remove(ours)
    os.write(device, b"after")
    time.sleep(0.15)
    assert r.drain() == []
    assert os.read(ours, 100) == b"after"  # still there: nobody read it
    r.add(ours, 4, True)  # watched again (a reopened port)
    os.write(device, b"again")
    assert wait_wake(r)
    assert [(s, d) for s, _, d, _ in r.drain()] == [(4, b"again")]


def test_closed_reader_refuses_work_and_closes_twice(reader) -> None:
    _, r = reader
    r.close()
    r.close()
    with pytest.raises(ValueError, match="closed"):
        r.drain()
    with pytest.raises(ValueError, match="closed"):
        r.add(0, 0, False)


def test_many_ports_at_once(reader, port) -> None:
    """Ports beyond the reader's slots are refused with an OSError, not lost silently."""
    _, r = reader
    pairs = [port() for _ in range(64)]
    for k, (_, ours) in enumerate(pairs):
        r.add(ours, k, True)
    extra = port()
    with pytest.raises(OSError):
        r.add(extra[1], 64, True)
    os.write(pairs[63][0], b"z")
    assert wait_wake(r)
    assert [(s, d) for s, _, d, _ in r.drain()] == [(63, b"z")]


def test_a_port_lost_twice_at_once_is_lost_once(tmp_path: Path) -> None:
    """At an unplug a polled device's write fails in Python while the thread's read fails
    too: one loss, one retry, whichever is told first."""
    assert READER is not None
    device, ours = pty.openpty()
    config = parse(f'[[sources]]\nname = "uwb"\ndriver = "nlink"\nport = "{os.ttyname(ours)}"\n'
                   'baud = 921600\n[anchors]\n"0" = [0, 0, 2]\n"1" = [5, 0, 2]\n'
                   '"2" = [0, 5, 2]\n"3" = [5, 5, 0.5]\n', "test")

    async def unplug() -> SerialSource:
        loop = asyncio.get_running_loop()
        queue = ReadQueue(Pipeline(config, []))
        clock = EpochClock()
        reads = ThreadReads(loop, clock, queue, READER)
        source = SerialSource(config.sources[0], queue, loop, clock, reads)
        source.start()
        assert source.info.state == "open"
        os.close(device)  # unplugged: the thread reads the end of the port ...
        time.sleep(0.2)  # (the loop held back, so that the thread's loss waits)
        source.lost(OSError(errno.EIO, "Input/output error"))  # ... and a write failed
        await asyncio.sleep(0.3)  # the thread's loss is taken now
        source.close()
        reads.close()
        return source

    source = asyncio.run(unplug())
    os.close(ours)
    assert source.info.losses == 1


class RawReads:
    """A sink that keeps each read's size (the pipeline's raw records)."""

    def __init__(self) -> None:
        self.sizes: list[int] = []

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        self.sizes.append(len(data))

    def frame(self, frame: object) -> None:
        """Frames are not kept."""

    def pose(self, pose: object) -> None:
        """Poses are not kept."""

    def status(self, t_ns: int, status: object) -> None:
        """Statuses are not kept."""

    def close(self) -> None:
        """Nothing to release."""


def test_an_imu_port_is_read_about_once_a_pose_and_its_tail_is_not_held() -> None:
    """A WitMotion's port (here a pty, 22 bytes every 5 ms): once its byte rate is known,
    VMIN makes a read wait for most of a pose period's bytes (80 % of 4.4 samples), so the
    port is read ~60 times a second, not ~200; when the device goes quiet with a tail below
    VMIN, the tail is read all the same (VMIN back to 0) within a tick or two."""
    assert READER is not None
    device, ours = pty.openpty()
    tty.setraw(device)
    config = parse(f'[[sources]]\nname = "imu"\ndriver = "wit"\nport = "{os.ttyname(ours)}"\n'
                   'baud = 921600\n[[sources]]\nname = "uwb"\ndriver = "nlink"\n'
                   'port = "/dev/not-started"\nbaud = 921600\n[anchors]\n"0" = [0, 0, 2]\n'
                   '"1" = [5, 0, 2]\n"2" = [0, 5, 2]\n"3" = [5, 5, 0.5]\n', "test")
    sink = RawReads()
    period_ns = config.pose_period_ns

    async def run() -> tuple[SerialSource, list[int], int]:
        loop = asyncio.get_running_loop()
        queue = ReadQueue(Pipeline(config, [sink]))
        clock = EpochClock()
        reads = ThreadReads(loop, clock, queue, READER)
        source = SerialSource(config.sources[0], queue, loop, clock, reads)
        source.start()
        writer = send(device, 600)  # 3 s
        batch = []
        while writer.is_alive():
            await asyncio.sleep(0.25)  # the daemon's tick
            reads.drain()
            source.batch_reads(clock.now_ns(), period_ns)
            batch.append(source.info.read_batch_bytes)
        writer.join()
        reads.drain()
        before_tail = sum(sink.sizes)
        os.write(device, b"\x55" * 40)  # a tail below VMIN, then nothing
        for _ in range(4):
            await asyncio.sleep(0.25)
            reads.drain()
            source.batch_reads(clock.now_ns(), period_ns)
        reads.drain()
        tail = sum(sink.sizes) - before_tail
        source.close()
        reads.close()
        return source, batch, tail

    source, batch, tail = asyncio.run(run())
    os.close(device)
    learned = [b for b in batch if b]
    assert learned and abs(learned[-1] - 0.8 * 22 * 200 * 0.02) <= 10
    late = sink.sizes[-40:]  # reads once batched: most of a pose period's bytes each
    assert sum(late) / len(late) >= learned[-1]  # (a tty gives 64 bytes a read: all taken)
    # every byte read in the end: the stream's last bytes below VMIN and the tail after them
    assert tail >= 40 and sum(sink.sizes) == 600 * 22 + 40
    assert source.info.read_batch_bytes == 0
