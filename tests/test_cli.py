"""The real ``uwbd`` command, run as a subprocess."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial
from procs import read_until

from drivers import PARSERS
from uwbd.cli import IMPORT_FORMATS
from uwbd.commands.tools import IMPORTERS
from uwbd.logs.reading import read_log

DATA = Path(__file__).parent / "data"
UWBD = [sys.executable, "-m", "uwbd"]


def run(*args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([*UWBD, *args], input=stdin, capture_output=True, timeout=60,
                          check=False)


def test_dump_prints_one_json_object_per_frame_and_counters_on_stderr() -> None:
    result = run("dump", "--driver", "nlink", str(DATA / "nlink-BADCK.bin"))
    assert result.returncode == 0, result.stderr
    (line,) = result.stdout.decode().splitlines()
    frame = json.loads(line)
    assert frame["type"] == "UwbRanges"
    assert frame["tag_position_m"] == [2.702, -0.091, 1.0]
    assert frame["ranges"][0] == {"anchor_id": 0, "range_m": 3.125, "quality": None,
                                  "anchor_position_m": None, "fp_rssi_dbm": None,
                                  "rx_rssi_dbm": None}
    stats = json.loads(result.stderr)["parser_stats"]
    assert stats["frames"] == 1 and stats["checksum_errors"] == 1
    assert stats["recent_errors"] == ["byte 0: nlink TagFrame0: checksum mismatch"]


def test_dump_reads_standard_input() -> None:
    data = (DATA / "wit-BADCK.bin").read_bytes()
    result = run("dump", "--driver", "wit", "-", stdin=data)
    assert result.returncode == 0
    frames = [json.loads(x) for x in result.stdout.decode().splitlines()]
    assert [f["type"] for f in frames] == ["ImuSample"] * 5
    assert set(frames[0]) >= {"t_ns", "acc_mps2", "gyro_rps", "temperature_c"}


def test_dump_missing_file_is_one_clear_line() -> None:
    result = run("dump", "--driver", "wit", "/nonexistent/capture.bin")
    assert result.returncode == 2
    assert result.stderr.decode().strip() == (
        "uwbd dump: cannot read /nonexistent/capture.bin: No such file or directory")


def test_dump_unknown_driver_is_one_clear_line() -> None:
    result = run("dump", "--driver", "witmotion", str(DATA / "wit-BADCK.bin"))
    assert result.returncode == 2
    (line,) = result.stderr.decode().splitlines()
    assert "unknown driver 'witmotion'" in line and "nlink" in line


def test_emulate_serves_ports_a_reader_can_open(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [*UWBD, "emulate", "--imu", "wit", "--uwb", "dwm1001", "--duration", "30",
         "--rest", "30", "--link-dir", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline().decode().split() for _ in range(2)]
        assert [(x[0], x[1]) for x in lines] == [("imu", "wit"), ("uwb", "dwm1001")]
        assert lines[0][2] == str(tmp_path / "imu")
        frames = {}
        for name, driver, path, *_ in lines:
            parser = PARSERS[driver]()
            with serial.Serial(path, 115200, timeout=0.1) as port:
                deadline = time.monotonic() + 5
                found: list[object] = []
                while len(found) < 3 and time.monotonic() < deadline:
                    found += parser.feed(port.read(4096))
            frames[name] = found
        assert len(frames["imu"]) >= 3 and len(frames["uwb"]) >= 3
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert set(json.loads(err)) == {"imu", "uwb"}  # fault/frame counts per device
    assert not (tmp_path / "imu").exists()  # stable names removed on exit


def test_emulate_rejects_a_bad_fault_window() -> None:
    result = run("emulate", "--unplug", "soon")
    assert result.returncode == 2
    assert "AT:DURATION" in result.stderr.decode()


@pytest.mark.parametrize("rest", ["-1", "nan", "1e9"])
def test_emulate_rejects_a_bad_rest(rest: str) -> None:
    result = run("emulate", "--rest", rest)
    assert result.returncode == 2
    (line,) = result.stderr.decode().splitlines()
    assert f"--rest {float(rest):g}: seconds from 0 to 3600" in line


def test_demo_runs_and_prints_a_summary() -> None:
    result = subprocess.run([*UWBD, "demo", "--duration", "2.5"], capture_output=True,
                            timeout=60, check=False, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    out = result.stdout.decode()
    assert result.returncode == 0, result.stderr
    assert "imu" in out and "summary:" in out
    assert "pose (" in out  # a live fused pose line
    assert "fused pose vs scenario truth: XY RMSE" in out
    # the log carries the truth, so `uwbd report` scores it as the summary suggests
    log = Path(out.split("try: uwbd report ")[1].split(")")[0])
    truth = list(read_log(log).json("/truth"))
    assert len(truth) > 20 and truth[0]["pose"]["position"]["z"] == 0.5


def test_demo_survives_ctrl_c_twice() -> None:
    """A second SIGINT during shutdown (a user pressing Ctrl-C again, or GNU timeout, which
    signals the process and its group) must not break the clean stop."""
    proc = subprocess.Popen([*UWBD, "demo"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    read_until(proc, b"pose (", timeout_s=30)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err.decode()
    assert b"Traceback" not in err
    assert b"fused pose vs scenario truth" in out


def test_the_version_said_is_the_installed_one() -> None:
    """``uwbd --version`` (a constant in uwbd/__init__.py, read without importlib.metadata)
    is the version the install recorded, which pyproject.toml takes from that constant."""
    from importlib.metadata import version  # noqa: PLC0415 - only this test needs it

    result = run("--version")
    assert result.returncode == 0
    assert result.stdout.decode().split()[:2] == ["uwbd", version("uwbd")]


def test_the_import_formats_offered_are_those_there_are() -> None:
    """The parser names the dataset layouts without importing the importers (start-up)."""
    assert set(IMPORT_FORMATS) == set(IMPORTERS)


def test_a_command_imports_only_its_own_layer() -> None:
    """``uwbd replay`` starts without the daemon, the simulator or the dataset importers."""
    check = ("import sys\n"
             "from uwbd.cli import main\n"
             "main(['replay', '/nonexistent.mcap'])\n"
             "print(sorted(m for m in ('asyncio', 'uwbd.service.daemon', 'uwbd.tools.simulator',"
             " 'uwbd.tools.importer', 'uwbd.commands.tools', 'uwbd.commands.service')"
             " if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_every_help_text_is_plain_text() -> None:
    """#45: what --help prints is for a terminal: no reStructuredText markup (``x``,
    :mod:`x`) from the docstrings it may be built from."""
    import re  # noqa: PLC0415

    from uwbd.cli import build_parser  # noqa: PLC0415

    parser = build_parser()
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    texts = {"uwbd": parser.format_help()}
    for action in subparsers:
        for name, sub in action.choices.items():
            texts[name] = sub.format_help()
    assert len(texts) > 10
    markup = re.compile(r"``|:(mod|func|class|meth|attr|data):`")
    found = {name: text for name, text in texts.items() if markup.search(text)}
    assert not found, found
