"""Every configuration key's meaning and default, in one table: ``docs/configuration.md`` and
``config/template.toml`` are generated from it and the schema (:mod:`.schema`: each key's
type and bounds), and a test fails when either file is stale or a key is missing here.

Regenerate both with ``python -m uwbd.config.reference``. Defaults are read from where the
code keeps them (the filter's settings, the IMU's noise, the ROS 2 names, the Zenoh
session, the config model's own).
Units are in the keys' names (``_m``, ``_s``, ``_mps2`` …) and said once per suffix.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from uwbd.config.model import (
    ALIGNER_WAIT_MS,
    IMU_NOISE_KEYS,
    LOG_DIRECTORY,
    POSE_RATE_HZ,
    ROTATE_MB,
    ROTATE_MINUTES,
    STALL_AFTER_S,
    STATUS_PERIOD_S,
)
from uwbd.config.ros2 import DEFAULT_TOPICS, LIVE_ONLY_WHEN_NAMED, TOPIC_KEYS, Ros2Settings
from uwbd.config.schema import TABLES, Key
from uwbd.config.zenoh_session import THIS_HOST_LISTEN, UWBD_DEFAULTS
from uwbd.fusion.checks.imu_check import ImuLimits
from uwbd.fusion.checks.intrinsics import ImuIntrinsics
from uwbd.fusion.core.noise import GRAVITY_MPS2, ImuNoise
from uwbd.fusion.settings import IDENTITY3, FilterConfig, HealthLimits, RobustPolicy

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "configuration.md"
TEMPLATE = ROOT / "config" / "template.toml"


@dataclass(frozen=True)
class Entry:
    """A key's default (``None``: unset, and ``unset`` says what that means) and meaning."""

    default: Any
    meaning: str
    unset: str = ""


_F, _H, _NOISE = FilterConfig(), HealthLimits(), ImuNoise()
_ROS2 = Ros2Settings()
UNITS = {"_mps2_rthz": "m/s²/√Hz", "_rps_rthz": "rad/s/√Hz", "_mps3_rthz": "m/s³/√Hz",
         "_rps2_rthz": "rad/s²/√Hz", "_mps2": "m/s²", "_rps": "rad/s", "_mps": "m/s",
         "_m": "m", "_s": "s", "_ms": "ms", "_hz": "Hz", "_mb": "MB (10⁶ bytes)",
         "_minutes": "min"}

REFERENCE: dict[str, dict[str, Entry]] = {
    "robot": {
        "name": Entry(None, "who writes the logs and publishes: in log file names "
                      "(`uwbd-<name>-<UTC time>.mcap`), the logs' metadata and the Zenoh "
                      "prefix; with mutual TLS, the certificate's common name",
                      "this machine's host name"),
        "nav_frame_id": Entry("enu", "the navigation frame's name (ENU) in poses and "
                              "transforms"),
        "body_frame_id": Entry("base_link", "the vehicle frame's name (forward-left-up), "
                               "child of the navigation frame"),
    },
    "imu": {
        "mounting": Entry([list(r) for r in IDENTITY3], "the rotation from the IMU's sensor "
                          "axes to the body's forward-left-up axes, as rows (an upside-down "
                          "sensor: `[[1, 0, 0], [0, -1, 0], [0, 0, -1]]`)"),
        "lever_arm_m": Entry(list(_F.lever_arm_m), "the UWB antenna's position from the IMU, "
                             "in body axes"),
        **{key: Entry(getattr(_NOISE, name), f"the IMU's {what} from its datasheet (the "
                      "default: a consumer MEMS part, with margin for vibration)")
           for key, name, what in (
               (k, v, w) for (k, v), w in zip(IMU_NOISE_KEYS.items(), (
                   "accelerometer white noise density", "gyro white noise density",
                   "accelerometer bias random walk", "gyro bias random walk"), strict=True))},
        "acc_full_scale_mps2": Entry(ImuLimits.acc_full_scale_mps2, "the accelerometer's "
                                     "full scale as the IMU is set: a sample at it is clipped "
                                     "and rejected (16 g)"),
        "gyro_full_scale_rps": Entry(ImuLimits.gyro_full_scale_rps, "the gyro's full scale "
                                     "as the IMU is set (2000 °/s)"),
        "acc_scale": Entry(list(ImuIntrinsics.acc_scale), "per sensor axis, the "
                           "accelerometer's scale in a_meas = scale · a_true + offset "
                           "(`uwbd calibrate-imu` measures it; each 0.8..1.2)"),
        "acc_offset_mps2": Entry(list(ImuIntrinsics.acc_offset_mps2), "per sensor axis, the "
                                 "accelerometer's offset (each within ±2)"),
        "gyro_offset_rps": Entry(list(ImuIntrinsics.gyro_offset_rps), "per sensor axis, the "
                                 "gyro's offset: ω = ω_meas − offset (each within ±0.5)"),
        "gyro_deadband_rps": Entry(ImuIntrinsics.gyro_deadband_rps, "a rate below this on an "
                                   "axis reads 0 (0: off; turns slower than the band are "
                                   "lost, so off by default)"),
        "gravity_mps2": Entry(GRAVITY_MPS2, "the local gravity the INS, the start at rest and "
                              "the rest test use (a warning outside 9.77..9.84)"),
    },
    "fusion": {
        "mode": Entry(_F.mode.value, "`tight`: every range is a measurement; `loose`: UWB "
                      "least-squares positions are"),
        "range_sigma_m": Entry(_F.range_sigma_m, "a range's white noise, 1 σ"),
        "range_bias_states": Entry(_F.range_bias_states, "estimate each anchor's antenna "
                                   "delay as a state (tight mode)"),
        "range_bias_sigma_m": Entry(_F.range_bias_sigma_m, "how far each anchor's antenna "
                                    "delay may be off, 1 σ (less after calibration)"),
        "tag_delay_sigma_m": Entry(_F.tag_delay_sigma_m, "how far the tag's antenna delay "
                                   "may be off, 1 σ: one offset common to every range"),
        "multipath_sigma_m": Entry(_F.multipath_sigma_m, "the ranges' error correlated over "
                                   "seconds (multipath), 1 σ, one state per anchor (0: white "
                                   "range noise, no states)"),
        "multipath_tau_s": Entry(_F.multipath_tau_s, "that error's correlation time"),
        "robust": Entry(RobustPolicy.enabled, "de-weight ranges that look like NLOS "
                        "(Geman–McClure)"),
        "nlos_onset_m": Entry(None, "a range this much longer than predicted is likelier "
                              "NLOS than noise: the robust weight's scale on the long side "
                              "(`uwbd calibrate-ranges` writes it)",
                              f"{RobustPolicy.c_long} × `range_sigma_m`"),
        "tag_side": Entry(_F.tag_side, "for anchors on one plane: `below`, `above`, or "
                          "`auto` (below anchors 1 m or higher, above lower ones; the ranges "
                          "decide where the anchors are far enough off one plane that their "
                          "delays could not fake the other side)"),
        "height_range_m": Entry(None, "`[lowest, highest]` the tag can be: settles the side "
                                "of a plane of anchors, a fix outside it is refused, and an "
                                "estimate outside it beyond its own σz is the fault "
                                "`height_implausible`",
                                "up to 3 m above the highest anchor, down to 3 m below the "
                                "lowest or 0.5 m below z 0 (the floor), whichever is lower"),
        "zupt": Entry(_F.zupt, "zero-velocity updates at rest"),
        "nhc": Entry(_F.nhc, "non-holonomic constraints: a ground vehicle does not move "
                     "sideways or vertically in body axes"),
        "known_height_m": Entry(None, "the tag's height where anchors on one horizontal "
                                "plane cannot tell it", "no height held"),
        "gate_probability": Entry(_F.gate_probability, "each measurement's χ² gate"),
        "min_anchors": Entry(_F.gating.min_anchors, "ranges a message "
                             "needs to be used"),
        "max_range_m": Entry(_F.gating.max_range_m, "a longer range is rejected"),
        "integrity_risk": Entry(_H.integrity_risk, "the protection levels' risk: the "
                                "probability that the error exceeds them"),
        "horizontal_alert_limit_m": Entry(_H.horizontal_alert_limit_m, "a pose is healthy "
                                          "only while its horizontal protection level is "
                                          "within this"),
        "vertical_alert_limit_m": Entry(_H.vertical_alert_limit_m, "and its vertical one "
                                        "within this"),
        "height_needed": Entry(_H.height_needed, "false: the robot needs no height (a ground "
                              "robot): healthy follows the horizontal alone, and a vertical "
                              "level over its limit is the note `height_uncertain`"),
        "range_bias_bound_m": Entry(_H.range_bias_bound_m, "each range's unmodelled bias at "
                                    "most, in the protection levels and the separation "
                                    "test's thresholds"),
        "false_alert_probability": Entry(_H.false_alert_probability, "the separation test's "
                                         "(docs/ekf.md §6) false alerts per test, shared "
                                         "over the anchors"),
        "lever_arm_sigma_m": Entry(_F.lever_arm_sigma_m, "> 0: the lever arm's error "
                                   "estimated as three states with this prior σ per axis "
                                   "(the status's `lever_arm_estimate_m`); 0: as given, "
                                   "and tested (the fault `lever_arm_inconsistent`)"),
    },
    "range_model": {
        "tag_degree": Entry(0, "the tag antenna's direction term, degree of its spherical "
                            "harmonics (0: off; 1: a phase centre; 2, 3: the finer pattern)"),
        "tag_coefficients_m": Entry(None, "that term's coefficients, as `uwbd "
                                    "calibrate-ranges` writes them", "none (degree 0)"),
        "tag_mounting": Entry([list(r) for r in IDENTITY3], "the tag antenna's axes to the "
                              "body's, as rows"),
        "anchor_delays_m": Entry(None, "each anchor's antenna delay, `{ id = delay }`",
                                 "none: `fusion.range_bias_states` estimates them"),
        "log_distance_m": Entry(0.0, "k of the delay k ln(d / 1 m) that grows with the "
                                "distance"),
        "anchor_degree": Entry(0, "the anchors' own direction term (needs each anchor's "
                               "`orientation_xyzw`; 0: off)"),
        "anchor_coefficients_m": Entry(None, "that term's coefficients", "none (degree 0)"),
        "calibrated_from": Entry(None, "the recording the model was fitted on (a note)",
                                 "not said"),
    },
    "pipeline": {
        "pose_rate_hz": Entry(POSE_RATE_HZ, "poses from the IMU between updates at this rate "
                              "(and at once after every epoch of several ranges)"),
        "status_period_s": Entry(STATUS_PERIOD_S, "how often the status is published"),
        "stall_after_s": Entry(STALL_AFTER_S, "a port open but silent this long is "
                               "`stalled` in the status"),
        "aligner_wait_ms": Entry(ALIGNER_WAIT_MS, "how long frames wait to be put in time "
                                 "order across ports"),
    },
    "log": {
        "directory": Entry(LOG_DIRECTORY, "where `uwbd run` writes its MCAP logs (a relative "
                           "path from the working folder; `--log-dir` overrides it)"),
        "rotate_mb": Entry(ROTATE_MB, "a new log file after this size"),
        "rotate_minutes": Entry(ROTATE_MINUTES, "and after this long"),
    },
    "zenoh": {
        "enabled": Entry(True, "publish over Zenoh"),
        "mode": Entry(UWBD_DEFAULTS["mode"], "`peer`, `client` (behind a router) or `router`"),
        "connect": Entry(None, "endpoints to dial (`\"tls/router.local:7447\"`)", "none"),
        "listen": Entry(None, "endpoints to listen on (`[]`: none)", f"`[\"{THIS_HOST_LISTEN}\"]`"
                        " (this host only) where neither `connect` nor `listen` is given, not "
                        "even empty, nor set in the Zenoh file; else none"),
        "multicast_scouting": Entry(UWBD_DEFAULTS["multicast_scouting"], "find and be found "
                                    "on the LAN by multicast (a warning without a Zenoh "
                                    "file)"),
        "prefix": Entry(None, "the key prefix of the pose, status and liveliness token",
                        "`uwbd/<robot name>`"),
        "config": Entry(None, "a Zenoh config file (JSON5: TLS, access control, "
                        "authentication) as the base; the keys above are set over it; a "
                        "relative path is from this config's folder", "none"),
    },
    "ros2": {
        "enabled": Entry(_ROS2.enabled, "publish the ROS 2 topics over rmw_zenoh's keys "
                         "(needs the `ros2` extra)"),
        "domain_id": Entry(None, "the ROS 2 domain", "`ROS_DOMAIN_ID`, else 0"),
        "namespace": Entry(_ROS2.namespace, "relative topic names resolve in it"),
        "node_name": Entry(_ROS2.node_name, "the node's name in `ros2 node list`"),
        "distro": Entry(_ROS2.distro, "the ROS 2 release the subscribers run "
                        "(`humble`: keys without a type hash)"),
        **{key: Entry(DEFAULT_TOPICS[role], f"the {role} topic's name (\"\": off)")
           for role, key in TOPIC_KEYS.items() if role not in LIVE_ONLY_WHEN_NAMED},
        **{key: Entry(None, f"the {role} topic's name (\"\": off, in bags too); live only "
                      f"when named (e.g. `\"{DEFAULT_TOPICS[role]}\"`)",
                      f"not live; `{DEFAULT_TOPICS[role]}` in a bag")
           for role, key in TOPIC_KEYS.items() if role in LIVE_ONLY_WHEN_NAMED},
    },
}

_HEAD = """# Configuration reference

<!-- generated by `python -m uwbd.config.reference` from uwbd/config/schema.py and
uwbd/config/reference.py: edit those, not this file (tests/test_docs.py fails when stale) -->

A config is one TOML file (`uwbd check-config FILE` says everything wrong with it at once).
`config/template.toml` holds every key below at its default, commented. Units are in the
keys' names: {units}. Frames: navigation ENU, body forward-left-up.

## `[[sources]]`

One table per serial device: `name` (any, unique: the log's `/raw/<name>`), `driver`
(`wit`, `dwm1001`, `dwm1001-tlv`, `nlink`, `nlink-node2`, `trek1000`, `trek1000-raw`:
[wire-formats.md](wire-formats.md)), `port` (`/dev/uwbd-imu`), `baud` (default 115200).

## `[anchors]`

`id = [x, y, z]` in m, ENU, per anchor; or `id = {{ position_m = [x, y, z], orientation_xyzw
= [qx, qy, qz, qw] }}` with the antenna's axes (for `[range_model] anchor_degree`).
"""


def _unit(key: str) -> str:
    for suffix, unit in UNITS.items():
        if key.endswith(suffix):
            return unit
    return ""


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return f"{value:.1f}"
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def _what(key: Key) -> str:
    said = key.kind.what
    if key.bounds is not None:
        said += f", {key.bounds.said()}"
    if key.choices:
        said += f": one of {', '.join(f'`{c}`' for c in key.choices)}"
    return said


def markdown() -> str:
    """``docs/configuration.md``."""
    units = ", ".join(f"`{s}` {u}" for s, u in UNITS.items())
    out = [_HEAD.format(units=units)]
    for section, entries in REFERENCE.items():
        out.append(f"\n## `[{section}]`\n\n| key | default | type | meaning |\n|---|---|---|---|")
        for name, entry in entries.items():
            default = entry.unset if entry.default is None else f"`{_toml(entry.default)}`"
            unit = _unit(name) if entry.default is not None else ""
            out.append(f"| `{name}` | {default}{f' {unit}' if unit else ''}"
                       f" | {_what(TABLES[section][name])} | {entry.meaning} |")
    return "\n".join(out) + "\n"


def template() -> str:
    """``config/template.toml``: every key at its default (unset ones commented out)."""
    out = ["# uwbd's configuration with every key at its default (docs/configuration.md says",
           "# what each means). Generated by `python -m uwbd.config.reference`: copy it, set",
           "# the sources and anchors of your robot, and check it with `uwbd check-config`.",
           "", "[[sources]]", 'name = "imu"', 'driver = "wit"', 'port = "/dev/uwbd-imu"',
           "baud = 115200", "", "[[sources]]", 'name = "uwb"', 'driver = "nlink"',
           'port = "/dev/uwbd-uwb"', "baud = 921600", "",
           "[anchors]  # id = [x, y, z] in m, ENU (the Nooploop tag's slots 0..7)",
           "0 = [0.0, 0.0, 2.5]", "1 = [10.0, 0.0, 2.5]", "2 = [10.0, 8.0, 2.5]",
           "3 = [0.0, 8.0, 0.5]"]
    for section, entries in REFERENCE.items():
        out += ["", f"[{section}]"]
        for name, entry in entries.items():
            unit = _unit(name)
            note = f"  # {unit}" if unit else ""
            if entry.default is None:
                out.append(f"# {name} = …  # unset: {entry.unset.replace('`', '')}")
            else:
                out.append(f"{name} = {_toml(entry.default)}{note}")
    return "\n".join(out) + "\n"


def main() -> None:
    """Write both files (``--check``: exit 1 if either is stale, writing nothing)."""
    stale = [(path, text) for path, text in ((DOC, markdown()), (TEMPLATE, template()))
             if not path.exists() or path.read_text(encoding="utf-8") != text]
    if "--check" in sys.argv[1:]:
        for path, _ in stale:
            print(f"{path}: stale; run python -m uwbd.config.reference", file=sys.stderr)
        raise SystemExit(1 if stale else 0)
    for path, text in stale:
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
