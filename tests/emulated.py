"""Config text for a daemon reading the emulator's two devices (a WitMotion IMU and a
Nooploop tag on pseudo-terminals, the circle scenario's anchors): the tests add their own
[robot] and [zenoh]."""

from __future__ import annotations

from drivers.emulator.scenario import DEFAULT_ANCHORS_M


def emulated_sources(ports: dict[str, str]) -> str:
    """``[[sources]]`` for the ``imu`` and ``uwb`` ports and the scenario's ``[anchors]``."""
    anchors = "\n".join(f'"{i}" = [{x}, {y}, {z}]' for i, (x, y, z) in enumerate(DEFAULT_ANCHORS_M))
    return f"""
[[sources]]
name = "imu"
driver = "wit"
port = "{ports['imu']}"
baud = 921600

[[sources]]
name = "uwb"
driver = "nlink"
port = "{ports['uwb']}"
baud = 921600

[anchors]
{anchors}
"""
