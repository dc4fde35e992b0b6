"""The configuration check: every problem at once, in the file's own key names, with the
semantics (anchors the driver needs, endpoints, rates, sigmas, the mounting) checked too;
``--set`` overrides; and ``uwbd check-config`` as a user runs it."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from drivers import PARSERS
from uwbd import config as cfgmod
from uwbd.config import ConfigError, SourceConfig, apply_overrides, load, parse, to_toml
from uwbd.config import checks as cfgchecks
from uwbd.fusion.filter import Filter
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.sim_presets import ceiling_room, handheld_async
from uwbd.tools.simulator import SimConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
UWBD = [sys.executable, "-m", "uwbd"]

IMU_SOURCE = """
[[sources]]
name = "imu"
driver = "wit"
port = "/dev/uwbd-imu"
baud = 921600
"""
UWB_SOURCE = """
[[sources]]
name = "uwb"
driver = "nlink"
port = "/dev/uwbd-uwb"
baud = 921600
"""
SOURCES = IMU_SOURCE + UWB_SOURCE
ANCHORS = """
[anchors]
"0" = [0.0, 0.0, 0.0]
"1" = [0.0, 8.0, 0.0]
"2" = [8.86, 8.0, 0.0]
"3" = [8.86, 0.0, 2.2]
"""
GOOD = SOURCES + ANCHORS


def problems(text: str, where: str = "cfg.toml") -> list[str]:
    with pytest.raises(ConfigError) as err:
        parse(text, where)
    return err.value.problems


def one_problem(text: str) -> str:
    found = problems(text)
    assert len(found) == 1, found
    return found[0]


def warnings(text: str) -> tuple[str, ...]:
    return parse(text, "cfg.toml").warnings


def with_section(section: str, body: str, base: str = GOOD) -> str:
    return f"{base}\n[{section}]\n{body}\n"


def uwbd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*UWBD, *args], capture_output=True, text=True, timeout=60,
                          check=False, cwd=ROOT)


# -- all at once, in the file's key names ---------------------------------------------------

SEVERAL = GOOD.replace('port = "/dev/uwbd-uwb"', 'port = "/dev/uwbd-imu"') + """
[imu]
mounting = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]

[fusion]
zupt = "yes"
zuptt = true
range_sigma_m = 0

[pipeline]
pose_rate_hz = "fast"

[zenoh]
listen = ["tcp/1.2.3.4"]
"""
SEVERAL_KEYS = ["sources[1].port", "imu.mounting", "fusion.zuptt", "fusion.zupt",
                "fusion.range_sigma_m", "pipeline.pose_rate_hz", "zenoh.listen[0]"]


def test_every_problem_is_reported_at_once_one_line_each() -> None:
    with pytest.raises(ConfigError) as err:
        parse(SEVERAL, "robot.toml")
    found = err.value.problems
    assert [line.split(": ")[1] for line in found] == SEVERAL_KEYS  # in the sections' order
    assert all(line.startswith("robot.toml: ") and "\n" not in line for line in found)
    assert str(err.value).splitlines() == found  # starts with the first problem's line
    assert 'fusion.zupt: expected true or false, got "yes" (a string)' in str(err.value)
    assert 'pipeline.pose_rate_hz: expected a number, got "fast" (a string)' in str(err.value)
    assert "imu.mounting: rows must be orthonormal with determinant +1 (a rotation sensor -> " \
           "body), got det -1.000" in str(err.value)
    assert "mounting_rotation" not in str(err.value)  # the filter's own names stay inside


@pytest.mark.parametrize(("body", "message"), [
    ('[fusion]\nmin_anchors = 2.5', "fusion.min_anchors: expected an integer, got 2.5 (a float)"),
    ('[fusion]\nrobust = 1', "fusion.robust: expected true or false, got 1 (an integer)"),
    ('[fusion]\nmode = 3', "fusion.mode: expected a string, got 3 (an integer)"),
    ('[log]\ndirectory = ["a"]', 'log.directory: expected a string, got ["a"] (an array of 1)'),
    ('[zenoh]\nconnect = "tcp/1.2.3.4:7447"', "zenoh.connect: expected an array of endpoint"),
    ('[imu]\nlever_arm_m = [0, 0]', "imu.lever_arm_m: expected [x, y, z] of finite numbers, "
                                    "got [0, 0] (an array of 2)"),
    ('[imu]\nmounting = [1, 0, 0]', "imu.mounting: expected 3 rows of 3 finite numbers"),
    ('[imu]\nacc_noise_mps2_rthz = "0.01"', "imu.acc_noise_mps2_rthz: expected a number, "
                                            'got "0.01" (a string)'),
    ('[pipeline]\nstatus_period_s = 1979-05-27',
     "pipeline.status_period_s: expected a number, got 1979-05-27 (a date)"),
    ("fusion = 3", "fusion: expected a table ([fusion]), got 3 (an integer)"),
])
def test_type_errors_say_the_type_expected(body: str, message: str) -> None:
    text = f"{body}\n{GOOD}" if body.startswith("fusion =") else f"{GOOD}\n{body}\n"
    assert message in one_problem(text)


@pytest.mark.parametrize(("text", "message"), [
    (with_section("fusion", "zuptt = true"), "fusion.zuptt: unknown key (did you mean zupt? "
                                             "known: false_alert_probability,"),
    (with_section("fusoin", "zupt = true"), "fusoin: unknown key (did you mean fusion? known: "),
    (with_section("fusion", "speed_of_light = 3"), "fusion.speed_of_light: unknown key (known: "),
    (GOOD.replace('baud = 921600\n\n[[sources]]', 'baud = 921600\nbaudrate = 1\n\n[[sources]]'),
     "sources[0].baudrate: unknown key (did you mean baud? known: baud, driver, name, port)"),
    (GOOD.replace('"nlink"', '"nlnk"'), 'sources[1].driver: unknown driver "nlnk" (did you mean '
                                        "nlink? known: wit, dwm1001, dwm1001-tlv, nlink, "
                                        "nlink-node2, trek1000, trek1000-raw)"),
])
def test_unknown_keys_list_the_known_and_suggest_the_closest(text: str, message: str) -> None:
    assert message in one_problem(text)


def test_a_toml_syntax_error_is_one_line_with_file_and_place() -> None:
    found = problems("[fusion\nzupt = true", "cfg.toml")
    assert len(found) == 1 and found[0].startswith("cfg.toml: ") and "line 1" in found[0]


# -- sources ------------------------------------------------------------------------------

def test_fusion_needs_a_uwb_source() -> None:
    assert one_problem(IMU_SOURCE + ANCHORS) == (
        "cfg.toml: sources: no UWB source (driver nlink, dwm1001, dwm1001-tlv, nlink-node2, "
        "trek1000, trek1000-raw)")


def test_a_config_without_sources_replays_and_imports() -> None:
    """What `uwbd import` writes, and a log without a config at all."""
    assert parse(ANCHORS, "cfg.toml").warnings == (
        "cfg.toml: sources: none: enough to replay or import a log, not to `uwbd run`",)
    assert parse("", "log (metadata)").anchors_m == {}


def test_a_uwb_source_without_an_imu_is_only_suspicious() -> None:
    assert warnings(UWB_SOURCE + ANCHORS) == (
        "cfg.toml: sources: no IMU source (driver wit): the filter needs IMU samples to start",)


@pytest.mark.parametrize(("change", "message"), [
    (('port = "/dev/uwbd-uwb"', 'port = "/dev/uwbd-imu"'),
     'sources[1].port: "/dev/uwbd-imu" is sources[0]\'s port too: one device cannot feed two'),
    (('port = "/dev/uwbd-uwb"', 'port = " "'), "sources[1].port: must not be empty"),
    (('port = "/dev/uwbd-uwb"\n', ""), "sources[1].port: required: a string"),
    (('name = "uwb"', 'name = "imu"'), 'sources[1].name: "imu" is sources[0]\'s name too'),
    (('baud = 921600\n\n[[sources]]', 'baud = 0\n\n[[sources]]'),
     "sources[0].baud: must be positive and at most 12000000, got 0"),
    (('baud = 921600\n\n[[sources]]', 'baud = 3000000000\n\n[[sources]]'),
     "sources[0].baud: must be positive and at most 12000000, got 3000000000"),
    (('baud = 921600\n\n[[sources]]', 'baud = 9223372036854775807\n\n[[sources]]'),
     "sources[0].baud: must be positive and at most 12000000, got 9223372036854775807"),
    (('baud = 921600\n\n[[sources]]', 'baud = "fast"\n\n[[sources]]'),
     'sources[0].baud: expected an integer, got "fast" (a string)'),
])
def test_source_errors(change: tuple[str, str], message: str) -> None:
    text = GOOD.replace(*change, 1)
    assert text != GOOD
    assert message in one_problem(text)


def test_a_non_standard_baud_rate_is_a_warning() -> None:
    text = GOOD.replace("baud = 921600", "baud = 921000", 1)
    assert warnings(text) == ("cfg.toml: sources[0].baud: 921000 is not a standard serial rate "
                              "(115200, 230400, 460800, 921600, ...)",)


def test_placeholder_ports_of_simulated_logs_may_repeat() -> None:
    assert parse(GOOD.replace("/dev/uwbd-imu", "simulated").replace("/dev/uwbd-uwb",
                                                                       "simulated")).sources


def test_every_driver_is_known_as_uwb_or_imu() -> None:
    assert sorted(cfgmod.UWB_DRIVERS + cfgmod.IMU_DRIVERS) == sorted(PARSERS)


# -- anchors ------------------------------------------------------------------------------

def anchors(*rows: str, sources: str = SOURCES, fusion: str = "") -> str:
    return sources + "\n[anchors]\n" + "\n".join(rows) + "\n" + (
        f"\n[fusion]\n{fusion}\n" if fusion else "")


FOUR = ('"0" = [0, 0, 0]', '"1" = [0, 8, 0]', '"2" = [8, 8, 0]', '"3" = [8, 0, 2]')


def test_a_ranges_only_driver_needs_three_anchors_and_warns_at_three() -> None:
    assert one_problem(anchors(*FOUR[:2])) == (
        "cfg.toml: anchors: the nlink driver (sources[1]) reports ranges only, so the anchor "
        "positions must be configured: 3 anchors at least (4 for a 3-D fix), got 2")
    assert "reports ranges only" in one_problem(anchors())
    assert warnings(anchors(*FOUR[:3])) == (
        "cfg.toml: anchors: 3 anchors give a 2-D fix only: add a 4th out of their plane, or set "
        "fusion.known_height_m",)
    assert warnings(anchors(*FOUR[:3], fusion="known_height_m = 0.3")) == ()
    assert warnings(anchors(*FOUR)) == ()


def test_drivers_that_report_anchor_positions_need_none_configured() -> None:
    for driver in ("dwm1001", "dwm1001-tlv"):
        config = parse(anchors(sources=SOURCES.replace("nlink", driver)))
        assert config.anchors_m == {} and config.warnings == ()


@pytest.mark.parametrize(("rows", "sources", "message"), [
    ((*FOUR, '"8" = [4, 4, 3]'), SOURCES,
     "anchors.8: id 8 is not one the UWB source can report (nlink (sources[1]): TagFrame0 "
     "slots 0..7)"),
    (('"0x10000" = [4, 4, 3]',), SOURCES.replace("nlink", "dwm1001"),
     "anchors.0x10000: id 65536 is not one the UWB source can report (dwm1001 (sources[1]): "
     "16-bit short ids 0..0xFFFF)"),
    ((*FOUR, '"4" = [0.0, 0.0, 0.01]'), SOURCES,
     "anchors.4: 0.010 m from anchors.0: anchors must be 0.05 m apart at least"),
    ((*FOUR, '"4" = [0, 0, 20000]'), SOURCES,
     "anchors.4: [0.0, 0.0, 20000.0]: more than 10 km from the origin"),
    ((*FOUR, '"a" = [1, 1, 1]'), SOURCES, 'anchors.a: not an integer id ("3", "0x1151")'),
    ((*FOUR, '"-1" = [1, 1, 1]'), SOURCES, "anchors.-1: not an integer id"),
    ((*FOUR, '"0x3" = [1, 1, 1]'), SOURCES, "anchors.0x3: the same id as anchors.3"),
    ((*FOUR, '"4" = [1, 1]'), SOURCES, "anchors.4: expected [x, y, z] of finite numbers, got "
                                       "[1, 1] (an array of 2)"),
    ((*FOUR, '"4" = [1, 1, inf]'), SOURCES, "anchors.4: expected [x, y, z] of finite numbers"),
])
def test_anchor_errors(rows: tuple[str, ...], sources: str, message: str) -> None:
    assert message in one_problem(anchors(*rows, sources=sources))


def test_anchors_all_at_one_point_are_each_reported() -> None:
    found = problems(anchors('"0" = [1, 1, 1]', '"1" = [1, 1, 1]', '"2" = [1, 1, 1]'))
    assert [line.split(": ")[1] for line in found] == ["anchors.1", "anchors.2", "anchors.2"]
    assert all("0.000 m from anchors." in line for line in found)


def test_anchors_on_one_line_are_suspicious() -> None:
    text = anchors('"0" = [0, 0, 2]', '"1" = [4, 0, 2]', '"2" = [8, 0, 2]', '"3" = [12, 0, 2]')
    assert warnings(text) == ("cfg.toml: anchors: all on one line: the tag's position around "
                              "that line is not observable",)


def test_anchor_ids_need_no_driver_without_a_uwb_source() -> None:
    assert parse(anchors('"0x1151" = [0, 0, 0]', sources="")).anchors_m == {0x1151: (0, 0, 0)}


def test_min_anchors_beyond_the_configured_anchors_is_an_error() -> None:
    assert one_problem(anchors(*FOUR, fusion="min_anchors = 5")) == (
        "cfg.toml: fusion.min_anchors: 5, but only 4 anchors are configured (the nlink driver "
        "ranges to configured anchors only)")
    assert parse(anchors(sources=SOURCES.replace("nlink", "dwm1001"), fusion="min_anchors = 5"))


# -- rates, sigmas, the IMU ---------------------------------------------------------------

@pytest.mark.parametrize(("section", "body", "message"), [
    ("pipeline", "pose_rate_hz = 0", "pipeline.pose_rate_hz: must be at least 0.1 and at most "
                                     "1000, got 0"),
    ("pipeline", "pose_rate_hz = 1001", "pipeline.pose_rate_hz: must be at least 0.1 and at "
                                        "most"),
    ("pipeline", "status_period_s = 0.01", "pipeline.status_period_s: must be at least 0.05 and "
                                           "at most 3600, got 0.01"),
    ("pipeline", "status_period_s = 7200", "pipeline.status_period_s: must be at least 0.05"),
    ("pipeline", "aligner_wait_ms = -1", "pipeline.aligner_wait_ms: must be zero or more and at "
                                         "most 1000, got -1"),
    ("pipeline", "aligner_wait_ms = 1500", "pipeline.aligner_wait_ms: must be zero or more"),
    ("fusion", "range_sigma_m = 0", "fusion.range_sigma_m: must be positive and at most 5"),
    ("fusion", "range_sigma_m = 6", "fusion.range_sigma_m: must be positive and at most 5, got 6"),
    ("fusion", "range_sigma_m = nan", "fusion.range_sigma_m: must be a finite number, got nan"),
    ("fusion", "gate_probability = 0.5", "fusion.gate_probability: must be more than 0.5 and less "
                                         "than 1, got 0.5"),
    ("fusion", "gate_probability = 1", "fusion.gate_probability: must be more than 0.5"),
    ("fusion", "min_anchors = 0", "fusion.min_anchors: must be at least 1 and at most 64"),
    ("fusion", "max_range_m = 0", "fusion.max_range_m: must be at least 0.1 and at most 10000"),
    ("fusion", "multipath_tau_s = 0", "fusion.multipath_tau_s: must be positive and at most 3600"),
    ("fusion", "multipath_sigma_m = -0.1", "fusion.multipath_sigma_m: must be zero or more"),
    ("fusion", "range_bias_sigma_m = -1", "fusion.range_bias_sigma_m: must be zero or more"),
    ("fusion", "tag_delay_sigma_m = inf", "fusion.tag_delay_sigma_m: must be a finite number"),
    ("fusion", "known_height_m = -inf", "fusion.known_height_m: must be a finite number, got -inf"),
    ("fusion", "mode = \"tite\"", 'fusion.mode: expected one of loose, tight, got "tite" (did you '
                                  "mean tight?)"),
    ("fusion", "tag_side = \"under\"", "fusion.tag_side: expected one of auto, below, above"),
    ("fusion", "height_range_m = [2, 1]", "fusion.height_range_m: expected [lowest, highest] in "
                                          "m, lowest < highest, got [2, 1]"),
    ("log", "rotate_mb = 0", "log.rotate_mb: must be at least 0.1 and at most 1000000, got 0"),
    ("log", "rotate_minutes = -5", "log.rotate_minutes: must be at least 1 and at most 1000000"),
    ("log", 'directory = ""', "log.directory: must not be empty"),
    ("imu", "gyro_noise_rps_rthz = -0.0002", "imu.gyro_noise_rps_rthz: must be more than 1e-08 "
                                             "and at most 1, got -0.0002"),
    ("imu", "acc_bias_walk_mps3_rthz = nan", "imu.acc_bias_walk_mps3_rthz: must be a finite"),
    ("imu", "acc_full_scale_mps2 = 0", "imu.acc_full_scale_mps2: must be at least 9 and at most"),
    # absurd but finite: an exponent slipped (#44)
    ("imu", "gyro_noise_rps_rthz = 1e300", "imu.gyro_noise_rps_rthz: must be more than 1e-08"),
    ("fusion", "range_bias_sigma_m = 1e300", "fusion.range_bias_sigma_m: must be zero or more "
                                             "and at most 100"),
    ("fusion", "max_range_m = 1e-300", "fusion.max_range_m: must be at least 0.1"),
    ("pipeline", "pose_rate_hz = 1e-300", "pipeline.pose_rate_hz: must be at least 0.1"),
    ("imu", "gyro_full_scale_rps = 1e-300", "imu.gyro_full_scale_rps: must be at least 0.5"),
    ("log", "rotate_mb = 1e300", "log.rotate_mb: must be at least 0.1 and at most 1000000"),
])
def test_rates_and_sigmas_must_make_sense(section: str, body: str, message: str) -> None:
    assert message in one_problem(with_section(section, body))


@pytest.mark.parametrize(("section", "body"), [
    ("pipeline", "pose_rate_hz = 1000\nstatus_period_s = 0.05\naligner_wait_ms = 0"),
    ("pipeline", "status_period_s = 3600\naligner_wait_ms = 1000"),
    ("fusion", "range_sigma_m = 1\ngate_probability = 0.51\nmin_anchors = 1\nmax_range_m = 0.1"),
    ("fusion", "multipath_sigma_m = 0\nrange_bias_sigma_m = 0\ntag_delay_sigma_m = 0"),
    ("fusion", "known_height_m = -2.5\nheight_range_m = [-3, 0]\ntag_side = \"below\""),
    ("log", "rotate_mb = 0.5\nrotate_minutes = 1"),
])
def test_values_at_the_edges_are_accepted(section: str, body: str) -> None:
    config = parse(with_section(section, body))
    if "max_range_m = 0.1" in body:  # ranges across the site are dropped: suspicious
        assert [w.split(": ")[1] for w in config.warnings] == ["fusion.max_range_m"]
    else:
        assert config.warnings == ()


@pytest.mark.parametrize(("section", "body", "warning"), [
    ("fusion", "range_sigma_m = 2", "fusion.range_sigma_m: 2 m: UWB ranges are good to about "
                                    "0.1 m; is it in metres?"),
    ("fusion", "tag_delay_sigma_m = 6", "fusion.tag_delay_sigma_m: 6 m: the filter holds "
                                        "antenna-delay uncertainty to 5 m"),
    ("fusion", "max_range_m = 5", "fusion.max_range_m: 5 m, less than the 12.1 m between the "
                                  "farthest anchors"),
    ("imu", "acc_noise_mps2_rthz = 2.0", "imu.acc_noise_mps2_rthz: 2 is more than 100x off the "
                                         "default 0.01"),
    ("imu", "gyro_bias_walk_rps2_rthz = 1e-7", "imu.gyro_bias_walk_rps2_rthz: 1e-07 is more than "
                                               "100x off the default 0.0001"),
    ("imu", "acc_full_scale_mps2 = 16", "imu.acc_full_scale_mps2: 16 m/s² is outside 2 g..64 g: "
                                        "is it in m/s²?"),
    ("imu", "gyro_full_scale_rps = 2000", "imu.gyro_full_scale_rps: 2000 rad/s is outside "
                                          "125 °/s..4000 °/s"),
    ("imu", "lever_arm_m = [0, 0, 12]", "imu.lever_arm_m: 12.0 m from the IMU to the antenna"),
])
def test_what_is_only_suspicious_is_a_warning(section: str, body: str, warning: str) -> None:
    found = warnings(with_section(section, body))
    assert len(found) == 1 and found[0].startswith(f"cfg.toml: {warning}"), found


def test_a_mounting_must_be_a_rotation() -> None:
    mirror = with_section("imu", "mounting = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]")
    assert one_problem(mirror) == (
        "cfg.toml: imu.mounting: rows must be orthonormal with determinant +1 (a rotation "
        "sensor -> body), got det -1.000")
    skewed = with_section("imu", "mounting = [[1, 0, 0], [0, 1, 0.1], [0, 0, 1]]")
    assert "got det 1.000, rows off orthonormal by up to 0.1" in one_problem(skewed)


def test_a_mounting_typed_to_four_places_becomes_the_nearest_rotation() -> None:
    text = with_section("imu", "mounting = [[0.7071, -0.7071, 0], [0.7071, 0.7071, 0], "
                               "[0, 0, 1]]")
    config = parse(text, "cfg.toml")
    assert config.warnings == ("cfg.toml: imu.mounting: rows are orthonormal to 2e-05 only: "
                               "the nearest rotation is used",)
    c = math.sqrt(0.5)
    assert [x for row in config.mounting for x in row] == pytest.approx(
        [c, -c, 0.0, c, c, 0.0, 0.0, 0.0, 1.0])
    Filter(config.filter_config())  # which checks it to 1e-6


def test_an_exact_mounting_is_kept_exactly() -> None:
    z_down = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
    config = parse(with_section("imu", f"mounting = {z_down}"))
    assert config.mounting == tuple(tuple(row) for row in z_down) and config.warnings == ()


def test_what_only_the_filter_rejects_is_said_in_config_keys(
        monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(_: object) -> None:
        raise ValueError("mounting_rotation must be a proper rotation matrix")

    monkeypatch.setattr(cfgchecks, "Filter", refuse)
    assert one_problem(GOOD) == ("cfg.toml: imu.mounting: the filter cannot use it: "
                                 "imu.mounting must be a proper rotation matrix")


# -- Zenoh --------------------------------------------------------------------------------

@pytest.mark.parametrize("endpoint", [
    "tcp/192.168.1.10:7447", "tcp/[::1]:7447", "tcp/[fe80::1%eth0]:7447", "tcp/0.0.0.0:0",
    "tcp/router.local:7447", "udp/224.0.0.224:7447", "tls/zenoh.example.com:7447",
    "quic/10.0.0.1:7447", "ws/localhost:8000", "unixsock-stream//run/uwbd/zenoh.sock",
    "serial//dev/ttyACM0#baudrate=115200", "unixpipe/uwbd", "tcp/192.168.1.10:7447#iface=eth0",
])
def test_zenoh_endpoints_that_parse(endpoint: str) -> None:
    # parsing reads no file: TLS's certificates (tests/test_zenoh_security.py) are this
    # machine's, checked by check-config and run, not by a replay elsewhere
    config = parse(with_section("zenoh", f'connect = ["{endpoint}"]\nlisten = ["{endpoint}"]'))
    assert config.zenoh["connect"] == [endpoint]
    # a plain listener beyond loopback is warned of (tests/test_zenoh_security.py), no more
    assert all("reachable from the network" in w for w in config.warnings), config.warnings


@pytest.mark.parametrize(("endpoint", "message"), [
    ("192.168.1.10:7447", "expected <protocol>/<address>, e.g. tcp/192.168.1.10:7447"),
    ("/tmp/zenoh.sock", "expected <protocol>/<address>"),
    ("tpc/1.2.3.4:7447", 'unknown protocol "tpc" (did you mean tcp? known: tcp, udp, tls,'),
    ("tcp/", "no address after tcp/"),
    ("tcp/1.2.3.4", "expected host:port, e.g. 192.168.1.10:7447"),
    ("tcp/1.2.3.4:", 'port "": expected 0..65535'),
    ("tcp/1.2.3.4:65536", 'port "65536": expected 0..65535'),
    ("tcp/1.2.3.4:http", 'port "http": expected 0..65535'),
    ("tcp/300.2.3.4:7447", '"300.2.3.4" is not an IPv4 address'),
    ("tcp/::1:7447", "an IPv6 address goes in brackets: [::1]:7447"),
    ("tcp/[::1]", "expected [IPv6 address]:port, e.g. [::1]:7447"),
    ("tcp/[::g]:7447", '"::g" is not an IPv6 address'),
    ("udp/my host:7447", '"my host" is not a host name'),
    ("unixsock-stream/tmp/z.sock", "expected an absolute socket path"),
    ("tcp/1.2.3.4:7447?=", "Zenoh: Endpoint metadata and config must contain at least one valid "
                           "parameter with a non-empty key: tcp/1.2.3.4:7447?="),
])
def test_zenoh_endpoints_that_do_not(endpoint: str, message: str) -> None:
    text = with_section("zenoh", f'connect = ["tcp/10.0.0.1:7447", "{endpoint}"]')
    assert one_problem(text).startswith(f'cfg.toml: zenoh.connect[1]: "{endpoint}": {message}')
    assert "endpoint.rs" not in one_problem(text)  # Zenoh's own words, not its source lines
    listen = with_section("zenoh", f'listen = ["{endpoint}"]')
    assert one_problem(listen).startswith(f'cfg.toml: zenoh.listen[0]: "{endpoint}": ')


def test_zenoh_mode_and_prefix() -> None:
    assert 'zenoh.mode: expected one of peer, client, router, got "server"' in one_problem(
        with_section("zenoh", 'mode = "server"'))
    assert one_problem(with_section("zenoh", 'mode = "client"')) == (
        'cfg.toml: zenoh.mode: "client" needs a zenoh.connect endpoint (a router or peer)')
    assert "zenoh.mode" in one_problem(with_section("zenoh", 'mode = "client"\nconnect = []'))
    assert parse(with_section("zenoh", 'mode = "client"\nconnect = ["tcp/10.0.0.1:7447"]'))
    assert "zenoh.prefix: \"uwbd/*\": no wildcards" in one_problem(
        with_section("zenoh", 'prefix = "uwbd/*"'))
    assert one_problem(with_section("zenoh", 'prefix = "uwbd//robot"')).startswith(
        'cfg.toml: zenoh.prefix: "uwbd//robot": Zenoh: Invalid Key Expr')
    assert parse(with_section("zenoh", 'prefix = "/uwbd/robot-1/"'))


def test_an_endpoint_twice_is_suspicious() -> None:
    text = with_section("zenoh", 'listen = ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7447"]')
    assert warnings(text) == ('cfg.toml: zenoh.listen[1]: "tcp/127.0.0.1:7447" is listed twice',)


# -- files: shipped, written by uwbd, broken ----------------------------------------------

@pytest.mark.parametrize("path", sorted((ROOT / "config").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_configs_pass(path: Path) -> None:
    config = load(path)
    expected = (f"{path}: sources: none: enough to replay or import a log, not to `uwbd run`",)
    assert config.warnings == (expected if not config.sources else ())
    assert config.text == path.read_text()


@pytest.mark.parametrize(("sim", "driver"), [
    (SimConfig(), "nlink"), (SimConfig(), "dwm1001-tlv"), (ceiling_room(0), "nlink"),
    (handheld_async(0), "dwm1001"),
])
def test_the_configs_uwbd_writes_into_logs_pass(sim: SimConfig, driver: str) -> None:
    text = simulation_toml(SimpleNamespace(config=sim), driver)  # type: ignore[arg-type]
    assert parse(text, "log").warnings == ()


def test_a_config_parses_into_typed_objects_and_is_written_back_the_same() -> None:
    text = with_section("imu", "mounting = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]\n"
                               "gyro_noise_rps_rthz = 0.0002",
                        anchors('"0" = [0.0, 0.0, 0.0]', '"0x1151" = [8.0, 0.0, 2.2]',
                                sources=SOURCES.replace("nlink", "dwm1001"),
                                fusion='mode = "loose"\nrange_sigma_m = 0.1'))
    c = parse(text, "cfg.toml")
    assert c.sources[0] == SourceConfig("imu", "wit", "/dev/uwbd-imu", 921600)
    assert c.anchors_m == {0: (0.0, 0.0, 0.0), 0x1151: (8.0, 0.0, 2.2)}
    assert c.filter_config().mode.value == "loose"
    assert c.filter_config().imu_noise.gyro == 0.0002  # from the datasheet ...
    assert c.filter_config().imu_noise.acc == 0.01  # ... or the default
    again = parse(to_toml(c.sources, c.anchors_m, c.mounting, c.lever_arm_m, c.fusion,
                          c.imu_noise))
    assert (again.sources, again.anchors_m, again.mounting, again.fusion, again.imu_noise) == (
        c.sources, c.anchors_m, c.mounting, c.fusion, c.imu_noise)


def test_crlf_and_a_byte_order_mark_read_as_before(tmp_path: Path) -> None:
    path = tmp_path / "cfg.toml"
    path.write_bytes(b"\xef\xbb\xbf" + GOOD.replace("\n", "\r\n").encode())
    config = load(path)
    assert config.text == GOOD and len(config.anchors_m) == 4


def test_check_config_reports_every_problem_and_exits_2(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(SEVERAL)
    result = uwbd("check-config", str(path))
    assert result.returncode == 2 and result.stdout == ""
    assert "Traceback" not in result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == len(SEVERAL_KEYS)
    for line, key in zip(lines, SEVERAL_KEYS, strict=True):
        assert f"{path}: {key}: " in line


def check_config_fails_in_one_line(path: Path, message: str) -> None:
    result = uwbd("check-config", str(path))
    assert result.returncode == 2, result.stdout
    assert "Traceback" not in result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert f"{path}: {message}" in result.stderr


def test_check_config_on_a_binary_file(tmp_path: Path) -> None:
    path = tmp_path / "random.bin"
    path.write_bytes(b"\xff" + os.urandom(4096))  # 0xff never occurs in UTF-8
    check_config_fails_in_one_line(path, "not a UTF-8 text file (byte 0xff at offset 0)")


def test_check_config_on_a_latin1_file(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(("# Caméra\n" + GOOD).encode("latin-1"))
    check_config_fails_in_one_line(path, "not a UTF-8 text file (byte 0xe9 at offset 5)")


def test_check_config_on_nul_bytes_a_missing_file_and_a_directory(tmp_path: Path) -> None:
    nul = tmp_path / "nul.toml"
    nul.write_bytes(b"\0" * 64)
    check_config_fails_in_one_line(nul, "not a text file (it holds NUL bytes)")
    check_config_fails_in_one_line(tmp_path / "missing.toml", "No such file or directory")
    check_config_fails_in_one_line(tmp_path, "Is a directory")


def test_a_file_too_large_for_a_config(tmp_path: Path) -> None:
    path = tmp_path / "big.toml"
    path.write_bytes(b"#" * (cfgmod.MAX_CONFIG_BYTES + 1))
    with pytest.raises(ConfigError, match=r"big\.toml: larger than 1 MiB: not a config file"):
        load(path)


def test_check_config_passes_a_good_file(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(GOOD)
    result = uwbd("check-config", str(path))
    assert result.returncode == 0, result.stderr
    assert f"{path}: ok (" in result.stdout


# -- overrides ----------------------------------------------------------------------------

SHIPPED = (ROOT / "config" / "witmotion-nooploop.toml").read_text()


def test_overrides_set_keys_and_record_the_config_used() -> None:
    sets = ["fusion.zupt=false", "fusion.range_sigma_m=0.2", 'fusion.tag_side="below"',
            "fusion.mode=loose", "anchors.3=[1,2,0.5]", "sources.uwb.port=/dev/ttyUSB1",
            "sources[0].baud=115200", 'zenoh.connect=["tcp/10.0.0.1:7447"]',
            "pipeline.pose_rate_hz = 100", "imu.gyro_noise_rps_rthz=2e-4"]
    text = apply_overrides(SHIPPED, sets, "robot.toml")
    assert text.startswith("# robot.toml with --set fusion.zupt=false --set ")
    config = parse(text, "robot.toml")
    assert config.text == text and config.warnings == ()
    assert config.fusion == {"mode": "loose", "zupt": False, "range_sigma_m": 0.2,
                             "tag_side": "below"}
    assert config.anchors_m[3] == (1.0, 2.0, 0.5) and len(config.anchors_m) == 8
    assert [(s.port, s.baud) for s in config.sources] == [("/dev/uwbd-imu", 115200),
                                                         ("/dev/ttyUSB1", 921600)]
    assert config.zenoh == {"mode": "peer", "connect": ["tcp/10.0.0.1:7447"],
                            "listen": ["tcp/127.0.0.1:7447"], "multicast_scouting": False}
    assert config.pipeline == {"pose_rate_hz": 100}
    assert config.imu_noise == {"gyro_noise_rps_rthz": 2e-4}
    # everything else as in the file
    original = parse(SHIPPED)
    assert (config.mounting, config.lever_arm_m, config.log) == (
        original.mounting, original.lever_arm_m, original.log)
    # and the text written is the whole document: applying nothing more changes nothing
    assert tomllib.loads(apply_overrides(text, ["fusion.zupt=false"], "x")) == tomllib.loads(text)


def test_no_overrides_keep_the_text_as_it_is() -> None:
    assert apply_overrides(SHIPPED, [], "robot.toml") == SHIPPED


def test_an_anchor_spelt_otherwise_is_replaced_not_doubled() -> None:
    text = apply_overrides(anchors(*FOUR[:3], '"0x3" = [8, 0, 2]'), ["anchors.3=[9, 0, 2]"], "x")
    assert parse(text).anchors_m[3] == (9.0, 0.0, 2.0)


def test_load_applies_overrides(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(GOOD)
    config = load(path, ["fusion.known_height_m=0.4"])
    assert config.fusion == {"known_height_m": 0.4} and "--set fusion.known_height_m" in config.text


@pytest.mark.parametrize(("item", "message"), [
    ("fusion.zupt", "--set fusion.zupt: expected section.key=value (fusion.zupt=false)"),
    ("=1", "--set =1: expected section.key=value"),
    ("fusion.zupt=maybe", '--set fusion.zupt=maybe: expected true or false, got "maybe" '
                          "(a string)"),
    ("fusion.zupt=", "--set fusion.zupt=: no value after ="),
    ("fusoin.zupt=true", "--set fusoin.zupt=true: unknown section 'fusoin' (did you mean fusion? "
                         "known: sources, anchors, imu, fusion, range_model, pipeline, log, "
                         "zenoh, robot, ros2)"),
    ("fusion=true", "--set fusion=true: expected fusion.<key>=value"),
    ("fusion.zupy=true", "--set fusion.zupy=true: unknown key fusion.zupy (did you mean zupt?"),
    ("fusion.range_sigma_m=0,2", "--set fusion.range_sigma_m=0,2: not a TOML value (Expected "
                                 "newline or end of document after a statement); quote a string"),
    ('fusion.mode="loose', "--set fusion.mode=\"loose: not a TOML value (Unterminated string)"),
    ("fusion.range_sigma_m=-1", "--set fusion.range_sigma_m=-1: must be positive and at most 5"),
    ("fusion.min_anchors=2.0", "--set fusion.min_anchors=2.0: expected an integer, got 2.0"),
    ("anchors.x=[1, 2, 3]", "--set anchors.x=[1, 2, 3]: an anchor id is an integer of 0 or more"),
    ("anchors.3=[1, 2]", "--set anchors.3=[1, 2]: expected [x, y, z] of finite numbers"),
    ("imu.mounting=[[1,0,0],[0,1,0],[0,0,-1]]",
     "--set imu.mounting=[[1,0,0],[0,1,0],[0,0,-1]]: rows must be orthonormal with determinant +1"),
    ("sources.gps.port=/dev/ttyUSB2", "--set sources.gps.port=/dev/ttyUSB2: no source named "
                                      "'gps' (sources: imu, uwb)"),
    ("sources[5].port=/dev/ttyUSB2", "--set sources[5].port=/dev/ttyUSB2: no sources[5] "
                                     "(2 sources)"),
    ("sources.uwb.speed=1", "--set sources.uwb.speed=1: unknown key 'speed' (known: name, driver"),
    ("sources.uwb.driver=nlnk", '--set sources.uwb.driver=nlnk: unknown driver "nlnk"'),
    ("sources.port=/dev/x", "--set sources.port=/dev/x: expected sources.<name>.<key>"),
])
def test_override_errors_name_the_override(item: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        apply_overrides(SHIPPED, [item], "robot.toml")
    assert str(err.value).startswith(message), str(err.value)
    assert len(err.value.problems) == 1


def test_overrides_on_a_file_that_is_not_toml() -> None:
    with pytest.raises(ConfigError, match=r"^robot\.toml: "):
        apply_overrides("[fusion", ["fusion.zupt=false"], "robot.toml")


def test_an_override_may_break_what_only_the_whole_file_tells() -> None:
    text = apply_overrides(SHIPPED, ['sources.uwb.port="/dev/uwbd-imu"'], "robot.toml")
    assert "sources[1].port: \"/dev/uwbd-imu\" is sources[0]'s port too" in one_problem(text)



def test_the_robot_names_its_keys_logs_and_frames(tmp_path: Path) -> None:
    named = cfgmod.parse('[robot]\nname = "r1"\nbody_frame_id = "r1/base_link"\n')
    assert (named.robot_name, named.zenoh_prefix) == ("r1", "uwbd/r1")
    assert (named.nav_frame_id, named.body_frame_id) == ("enu", "r1/base_link")
    assert cfgmod.parse("").robot_name == cfgmod.default_robot_name()
    with pytest.raises(cfgmod.ConfigError) as err:
        cfgmod.parse('[robot]\nname = "robot one"\nnav_frame_id = ""\n', "cfg.toml")
    assert err.value.problems == [
        "cfg.toml: robot.name: expected a name of letters, digits, '-' and '_', at most 64 "
        "(\"robot1\"), got \"robot one\" (a string)",
        "cfg.toml: robot.nav_frame_id: expected a frame name of letters, digits, '_', '-', '.' "
        "and '/' (\"base_link\"), got \"\" (a string)"]
