"""The shipped systemd unit and udev rule, checked with systemd's own tools where they exist.

``systemd-analyze security --offline=yes`` (systemd >= 250) scores the unit file without a
running systemd; ``systemd-analyze verify`` loads it as systemd would and prints every key it
does not know or value it cannot parse; ``udevadm verify`` (systemd >= 254) checks rules files.
A tool that is missing or too old skips its test with the reason; the plain parse of the rules
always runs.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "systemd" / "uwbd.service"
RULES = ROOT / "systemd" / "99-uwbd.rules"
INSTALLED_BINARY = "/opt/uwbd/.venv/bin/uwbd"
MAX_EXPOSURE = 4.0
# directives the score must show as satisfied: losing one of these is a regression even when
# the total stays under the limit
MUST_PASS = ("CapabilityBoundingSet=", "SystemCallFilter=", "SystemCallArchitectures=",
             "MemoryDenyWriteExecute=", "RestrictNamespaces=", "ProtectProc=", "ProcSubset=",
             "NoNewPrivileges=", "ProtectSystem=", "ProtectClock=", "ProtectKernelLogs=",
             "RemoveIPC=")


def systemd_analyze() -> str:
    path = shutil.which("systemd-analyze")
    if path is None:
        pytest.skip("systemd-analyze is not installed")
    return path


def run(*cmd: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=60,
                          check=False)


def security(tmp_path: Path, unit_text: str) -> tuple[float, str]:
    """(overall exposure, full output) of ``systemd-analyze security --offline=yes``."""
    tool = systemd_analyze()
    copy = tmp_path / "uwbd.service"  # alone in its directory: no drop-ins picked up
    copy.write_text(unit_text)
    result = run(tool, "security", "--offline=yes", "--no-pager", copy)
    out = result.stdout + result.stderr
    if "offline" in out.lower() and ("unrecognized" in out or "unknown" in out.lower()):
        pytest.skip(f"systemd-analyze cannot analyse offline (needs systemd >= 250): {out[:200]}")
    match = re.search(r"Overall exposure level for uwbd\.service: (\d+(?:\.\d+)?)", out)
    assert match, f"no overall exposure line (exit {result.returncode}):\n{out}"
    return float(match[1]), out


def test_security_exposure_is_at_most_4(tmp_path: Path) -> None:
    score, out = security(tmp_path, UNIT.read_text())
    assert score <= MAX_EXPOSURE, out
    failed = [line for line in out.splitlines() if line.lstrip().startswith("✗")]
    for directive in MUST_PASS:
        assert not [line for line in failed if f" {directive}" in line], (directive, out)


def test_security_score_comes_from_the_sandbox(tmp_path: Path) -> None:
    """The analysis really reads this file: without its sandbox lines the unit scores unsafe."""
    sandbox = re.compile(r"(Protect|Private|Restrict|SystemCall|Capability|Ambient|Device|"
                         r"IPAddress|MemoryDeny|NoNew|Lock|Remove|ProcSubset|UMask)")
    bare = "\n".join(line for line in UNIT.read_text().splitlines() if not sandbox.match(line))
    assert "ExecStart=" in bare and "SupplementaryGroups=" in bare
    unsandboxed, out = security(tmp_path, bare)
    assert unsandboxed >= 8.0, out


def verify(tmp_path: Path, unit_text: str) -> tuple[int, str]:
    """(exit code, output) of ``systemd-analyze verify`` for the unit with a stand-in binary.

    The unit names the binary where a deployment installs it; verify refuses a unit whose
    ExecStart does not exist, which here would say nothing about the unit itself. So a copy runs
    a stand-in executable at a path that exists; everything else is the shipped text.
    """
    tool = systemd_analyze()
    stand_in = tmp_path / "uwbd"
    stand_in.write_text("#!/bin/sh\nexit 0\n")
    stand_in.chmod(0o755)
    assert unit_text.count(INSTALLED_BINARY) == 1
    copy = tmp_path / "uwbd.service"
    copy.write_text(unit_text.replace(INSTALLED_BINARY, str(stand_in)))
    result = run(tool, "verify", copy)
    return result.returncode, (result.stdout + result.stderr).strip()


def test_verify_reports_nothing(tmp_path: Path) -> None:
    # the tool does flag mistakes here (else an empty report would prove nothing)
    _, typo = verify(tmp_path, UNIT.read_text().replace("UMask=", "UMaskk=", 1))
    assert "Unknown key" in typo and "UMaskk" in typo, typo
    assert verify(tmp_path, UNIT.read_text()) == (0, "")


def test_optional_device_dependencies_parse_and_name_the_udev_links(tmp_path: Path) -> None:
    text = UNIT.read_text()
    optional = re.findall(r"^#((?:BindsTo|After)=dev-.*)$", text, re.MULTILINE)
    assert len(optional) == 2, optional
    for line in optional:
        assert line.split("=", 1)[1].split() == [
            r"dev-uwbd\x2dimu.device", r"dev-uwbd\x2duwb.device"]
    escape = shutil.which("systemd-escape")
    if escape is not None:  # the names are systemd's for the links the rules create
        for link in ("/dev/uwbd-imu", "/dev/uwbd-uwb"):
            name = run(escape, "-p", "--suffix=device", link).stdout.strip()
            assert name in optional[0].split("=", 1)[1].split(), (link, name)
    enabled = text
    for line in optional:
        enabled = enabled.replace(f"#{line}\n", f"{line}\n")
    assert enabled.count("\nBindsTo=dev-") == 1
    assert verify(tmp_path, enabled) == (0, "")


# --- udev rules ---

TOKEN = re.compile(r'\s*([A-Z_]+(?:\{[^}]+\})?)\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*(,|$)')
MATCH_ONLY = ("SUBSYSTEM", "SUBSYSTEMS", "KERNEL", "KERNELS", "ATTRS", "ATTR", "DRIVERS",
              "ACTION")


def rule_lines() -> list[list[tuple[str, str, str]]]:
    """Each device line of the rules as (key, operator, value) tokens; the whole line must parse."""
    lines = []
    for number, raw in enumerate(RULES.read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        assert not line.endswith("\\"), f"line {number}: continuation lines not expected"
        tokens, pos = [], 0
        while pos < len(line):
            m = TOKEN.match(line, pos)
            assert m, f"line {number}: cannot parse at {line[pos:]!r}"
            tokens.append((m[1], m[2], m[3]))
            pos = m.end()
        for key, op, _ in tokens:
            if key.split("{")[0] in MATCH_ONLY:
                assert op in ("==", "!="), f"line {number}: {key}{op} assigns a match-only key"
        lines.append(tokens)
    return lines


def test_udevadm_verify() -> None:
    udevadm = shutil.which("udevadm")
    if udevadm is None:
        pytest.skip("udevadm is not installed")
    if run(udevadm, "verify", "--help").returncode != 0:
        pytest.skip("this udevadm has no verify command (systemd >= 254)")
    result = run(udevadm, "verify", "--resolve-names=never", RULES)
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_rule_ignores_modemmanager_and_tags_for_systemd() -> None:
    lines = rule_lines()
    assert len(lines) >= 3
    for tokens in lines:
        assert ("SUBSYSTEM", "==", "tty") in tokens, tokens
        assert ("ENV{ID_MM_DEVICE_IGNORE}", "=", "1") in tokens, tokens
        assert ("TAG", "+=", "systemd") in tokens, tokens
        assert ("GROUP", "=", "dialout") in tokens, tokens  # the group the unit's user has
        assert ("MODE", "=", "0660") in tokens, tokens
        links = [v for k, op, v in tokens if k == "SYMLINK" and op == "+="]
        assert links in (["uwbd-imu"], ["uwbd-uwb"]), tokens


def usb_id(tokens: list[tuple[str, str, str]]) -> tuple[str, str]:
    found = dict((k, v) for k, op, v in tokens if op == "==")
    return found.get("ATTRS{idVendor}", ""), found.get("ATTRS{idProduct}", "")


def test_ch340_is_matched_by_port_not_serial() -> None:
    ch340 = [t for t in rule_lines() if usb_id(t) == ("1a86", "7523")]
    assert len(ch340) == 1
    (tokens,) = ch340
    keys = {k for k, _, _ in tokens}
    assert "ATTRS{serial}" not in keys  # a CH340 has no serial number to match
    port = [v for k, op, v in tokens if k in ("ENV{ID_PATH}", "KERNELS") and op == "=="]
    assert port and all(port), tokens
    assert ("SYMLINK", "+=", "uwbd-imu") in tokens


def test_uwb_adapters_are_kept() -> None:
    ids = {usb_id(t): t for t in rule_lines()}
    for usb in (("10c4", "ea60"), ("1366", "0105")):  # CP210x (Nooploop), SEGGER (DWM1001)
        assert usb in ids, ids.keys()
        assert ("SYMLINK", "+=", "uwbd-uwb") in ids[usb]
