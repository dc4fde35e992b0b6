"""Bad inputs, by group (#44): log times out of range, numbers that are not finite or not
integers, missing fields, bytes that are not UTF-8, FIFOs, nesting past any config, NUL
bytes, names too long, finite but absurd values. Each is one line and the right exit code
(2: the input is wrong; 1: nothing came of it), or the record is skipped with a warning and
the rest goes on; no traceback, no hang, nothing lost that was intact."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import pytest
from emulated import emulated_sources
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from procs import one_line, uwbd

from uwbd.tools.logtools import write_simulation
from uwbd.tools.sim_presets import segments_for
from uwbd.tools.simulator import SimConfig, simulate

Mutate = Callable[[str, int, int, bytes], tuple[int, bytes]]


@pytest.fixture(scope="module")
def full_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated run replayed to a log with every channel: raw reads, /imu, /uwb,
    /pose, /truth."""
    folder = tmp_path_factory.mktemp("bad")
    sim = folder / "sim.mcap"
    write_simulation(simulate(SimConfig(seed=4, segments=segments_for(12.0))), sim)
    done = uwbd("replay", str(sim), "-o", str(folder / "full.mcap"))
    assert done.returncode == 0, done.stderr
    return folder / "full.mcap"


def rewrite(src: Path, dst: Path, mutate: Mutate) -> Path:
    """``src`` copied (schemas, channels, metadata) with ``mutate(topic, k, log_time, data)``
    applied to each message, ``k`` its index on its topic."""
    with src.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    with src.open("rb") as f:
        messages = [(c.topic, m.log_time, m.data)
                    for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    with dst.open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="tests")
        schemas = {0: 0} | {s.id: w.register_schema(s.name, s.encoding, s.data)
                            for s in summary.schemas.values()}
        channels = {c.topic: w.register_channel(c.topic, c.message_encoding,
                                                schemas[c.schema_id], dict(c.metadata))
                    for c in summary.channels.values()}
        for name, data in metadata:
            w.add_metadata(name, data)
        seen: dict[str, int] = {}
        for topic, time_ns, record in messages:
            k = seen[topic] = seen.get(topic, -1) + 1
            t, data = mutate(topic, k, time_ns, record)
            w.add_message(channels[topic], t, data, min(t, 2**64 - 1))
        w.finish()
    return dst


def json_edit(topic: str, edit: Callable[[dict[str, object]], object]) -> Mutate:
    """The fifth record on ``topic`` edited (a dict in, its new JSON text or bytes out)."""
    def mutate(t_topic: str, k: int, t: int, data: bytes) -> tuple[int, bytes]:
        if t_topic != topic or k != 5:
            return t, data
        new = edit(json.loads(data))
        if isinstance(new, str):  # JSON text as written (with Infinity, say)
            return t, new.encode()
        return t, new if isinstance(new, bytes) else json.dumps(new).encode()
    return mutate


def with_t_ns(value: object) -> Callable[[dict[str, object]], object]:
    return lambda d: {**d, "t_ns": value}


def no_traceback(result: object) -> None:
    stderr = getattr(result, "stderr", "")
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr


@pytest.mark.parametrize(("name", "mutate", "commands"), [
    # log times out of range: a read past 2^63 ns is left out, the rest replays
    ("raw time past int64", lambda topic, k, t, d: (
        (2**64 - 1, d) if topic.startswith("/raw/") and k == 7 else (t, d)),
     (("replay",), ("survey",))),
    # numbers not finite, not integers, out of range
    ("imu t_ns inf", json_edit("/imu", lambda d: json.dumps({**d, "t_ns": float("inf")})),
     (("report", "-o", "plots"), ("export", "--ros2", "bag"))),
    ("truth t_ns 1e30", json_edit("/truth", with_t_ns(1e30)),
     (("calibrate-ranges",), ("export", "--ros2", "bag"))),
    ("pose t_ns -5", json_edit("/pose", with_t_ns(-5)), (("export", "--ros2", "bag"),)),
    ("pose t_ns null", json_edit("/pose", with_t_ns(None)), (("export", "--ros2", "bag"),)),
    ("truth t_ns string", json_edit("/truth", with_t_ns("soon")),
     (("export", "--ros2", "bag"),)),
    ("truth position nan", json_edit("/truth", lambda d: json.dumps(
        {**d, "pose": {**d["pose"], "position": {"x": float("nan"), "y": 0, "z": 0}}})),
     (("calibrate-ranges",),)),
    # missing fields
    ("truth without pose", json_edit("/truth", lambda d: {"t_ns": d["t_ns"]}),
     (("export", "--ros2", "bag"), ("calibrate-ranges",))),
    # encodings
    ("truth not utf-8", json_edit("/truth", lambda d: b"\xff\xfe{not json"),
     (("export", "--ros2", "bag"), ("calibrate-ranges",))),
    ("pose not utf-8", json_edit("/pose", lambda d: b"\xff\xfe"), (("export", "--ros2", "bag"),)),
    ("imu a JSON string", json_edit("/imu", lambda d: b'"an imu sample"'),
     (("export", "--ros2", "bag"),)),
])
def test_a_bad_record_is_skipped_and_the_rest_goes_on(
        tmp_path: Path, full_log: Path, name: str, mutate: Mutate,
        commands: tuple[tuple[str, ...], ...]) -> None:
    bad = rewrite(full_log, tmp_path / "bad.mcap", mutate)
    for command in commands:
        args = [command[0], str(bad), *[str(tmp_path / a) if a in ("plots", "bag") else a
                                        for a in command[1:]]]
        done = uwbd(*args, timeout=120)
        no_traceback(done)
        if command[0] == "report":  # (it does not read that record: it only must not fail)
            assert done.returncode == 0, (name, args, done.stderr)
            continue
        # calibrate-ranges then says the 12 s recording is too short for a calibration
        assert done.returncode == (2 if command[0] == "calibrate-ranges" else 0), (
            name, args, done.stderr)
        assert "skipped" in done.stderr or "left out" in done.stderr, (name, args, done.stderr)


def test_reads_all_at_one_log_time_are_said_and_exit_1(tmp_path: Path, full_log: Path) -> None:
    bad = rewrite(full_log, tmp_path / "zero.mcap",
                  lambda topic, k, t, d: (0, d) if topic.startswith("/raw/") else (t, d))
    one_line(uwbd("replay", str(bad), "-o", str(tmp_path / "out.mcap")), 1,
             "no pose came out", "every read has the log time 0 ns", "nothing written")
    assert not (tmp_path / "out.mcap").exists()


def test_a_fifo_as_log_or_config_is_refused_without_waiting(tmp_path: Path,
                                                              full_log: Path) -> None:
    """A FIFO nobody writes would block a reader for ever: refused at once, one line."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for args in (("replay", str(fifo)), ("report", str(fifo)), ("survey", str(fifo)),
                 ("recover", str(fifo), "-o", str(tmp_path / "r.mcap")),
                 ("calibrate-ranges", str(fifo)), ("export", str(fifo), "--ros2",
                                                   str(tmp_path / "bag"))):
        one_line(uwbd(*args, timeout=30), 2, str(fifo), "not a regular file")
    for args in (("check-config", str(fifo)), ("run", "-c", str(fifo)),
                 ("replay", str(full_log), "-c", str(fifo))):
        one_line(uwbd(*args, timeout=30), 2, str(fifo), "not a regular file")


CONFIG = emulated_sources({"imu": "/dev/ttyUSB7", "uwb": "/dev/ttyUSB8"})


@pytest.mark.parametrize(("text", "said"), [
    # nesting past any config: TOML's parser recursion
    ("a = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
    ("a = " + "{x = " * 5000 + "1" + "}" * 5000 + "\n", "nested too deeply"),
    # NUL characters no path or name can hold
    (CONFIG + '[log]\ndirectory = "logs\\u0000x"\n', "log.directory"),
    (CONFIG.replace("/dev/ttyUSB7", "/dev/tty\\u0000USB7"), "sources[0].port"),
    # a name longer than a key expression or a file name takes
    (CONFIG + f'[robot]\nname = "{"r" * 10_000}"\n', "robot.name"),
    # finite but absurd
    (CONFIG + "[fusion]\nrange_bias_sigma_m = 1e300\n", "fusion.range_bias_sigma_m"),
    (CONFIG + "[imu]\ngyro_full_scale_rps = 1e-300\n", "imu.gyro_full_scale_rps"),
])
def test_a_config_past_any_sense_is_one_line_at_check_and_at_run(
        tmp_path: Path, text: str, said: str) -> None:
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text)
    one_line(uwbd("check-config", str(cfg)), 2, said)
    one_line(uwbd("run", "-c", str(cfg), "--duration", "1", "--log-dir",
                  str(tmp_path / "logs")), 2, said)
    assert not (tmp_path / "logs").exists()
