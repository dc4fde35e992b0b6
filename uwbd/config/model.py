"""What a parsed config is: :class:`Config` and its :class:`SourceConfig` entries, the
:class:`ConfigError` a bad file raises, and :meth:`Config.filter_config` with the maps from
``[imu]`` keys to the filter's fields."""

from __future__ import annotations

import socket
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from uwbd.config.ros2 import Ros2Settings, settings_of
from uwbd.fusion.checks.gating import GatingPolicy
from uwbd.fusion.checks.imu_check import ImuLimits
from uwbd.fusion.checks.intrinsics import ImuIntrinsics
from uwbd.fusion.core.noise import GRAVITY_MPS2, ImuNoise
from uwbd.fusion.models.range_model import RangeModel
from uwbd.fusion.settings import IDENTITY3, FilterConfig, HealthLimits, Mode, RobustPolicy

Vec3 = tuple[float, float, float]
# [imu] key -> ImuNoise field
IMU_NOISE_KEYS = {"acc_noise_mps2_rthz": "acc", "gyro_noise_rps_rthz": "gyro",
                  "acc_bias_walk_mps3_rthz": "acc_bias", "gyro_bias_walk_rps2_rthz": "gyro_bias"}
IMU_LIMIT_KEYS = ("acc_full_scale_mps2", "gyro_full_scale_rps")  # ImuLimits fields
# [imu] key -> ImuIntrinsics field (the same names): a_true = (a_meas − offset) / scale
IMU_INTRINSIC_VECTORS = ("acc_scale", "acc_offset_mps2", "gyro_offset_rps")
IMU_INTRINSIC_KEYS = (*IMU_INTRINSIC_VECTORS, "gyro_deadband_rps", "gravity_mps2")
# the defaults of the [log] and [pipeline] keys (uwbd.config.reference says each)
LOG_DIRECTORY = "logs"
ROTATE_MB = 256.0
ROTATE_MINUTES = 60.0
POSE_RATE_HZ = 1e9 / FilterConfig.pose_period_ns  # (50: the filter's policy period's)
STATUS_PERIOD_S = 1.0
ALIGNER_WAIT_MS = 0.0
STALL_AFTER_S = 1.0  # no byte this long: the port is stalled
# [fusion] keys that are HealthLimits fields (the same names): the protection levels' risk
# and alert limits, whether the height counts, the ranges' bias bound, the separation
# test's false alerts
_HEALTH_KEYS = ("integrity_risk", "horizontal_alert_limit_m", "vertical_alert_limit_m",
                "height_needed", "range_bias_bound_m", "false_alert_probability")
# [fusion] keys that are FilterConfig fields (the same names), taken as they are
_FILTER_KEYS = ("lever_arm_sigma_m", "range_sigma_m", "range_bias_states", "range_bias_sigma_m",
                "tag_delay_sigma_m", "multipath_tau_s", "tag_side", "zupt", "nhc",
                "known_height_m", "gate_probability")


def vec3(value: Sequence[float]) -> Vec3:
    return (float(value[0]), float(value[1]), float(value[2]))


class ConfigError(ValueError):
    """Configuration problems, each a line ``"{file}: {key}: {what}"``.

    ``problems`` lists them all; ``str()`` is them joined by newlines, so it starts with the
    first. ``warnings`` holds what was only suspicious in the same file."""

    def __init__(self, problems: str | Sequence[str], warnings: Sequence[str] = ()) -> None:
        self.problems: list[str] = [problems] if isinstance(problems, str) else list(problems)
        self.warnings: list[str] = list(warnings)
        super().__init__("\n".join(self.problems))


def default_robot_name() -> str:
    """This machine's host name, with what a key expression or file name cannot hold as
    ``_``."""
    host = "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname())
    return host or "robot"


@dataclass(frozen=True)
class SourceConfig:
    name: str
    driver: str
    port: str
    baud: int = 115200


@dataclass(frozen=True)
class Config:
    sources: tuple[SourceConfig, ...] = ()
    anchors_m: dict[int, Vec3] = field(default_factory=dict)
    # the anchors given with an orientation: their axes -> navigation frame, as rows
    anchor_axes: dict[int, tuple[Vec3, Vec3, Vec3]] = field(default_factory=dict)
    mounting: tuple[Vec3, Vec3, Vec3] = IDENTITY3
    lever_arm_m: Vec3 = (0.0, 0.0, 0.0)
    imu_noise: dict[str, float] = field(default_factory=dict)  # [imu] noise keys given
    imu_limits: dict[str, float] = field(default_factory=dict)  # [imu] full-scale keys given
    # [imu] intrinsics and gravity given (IMU_INTRINSIC_KEYS), vectors as Vec3
    imu_intrinsics: dict[str, Any] = field(default_factory=dict)
    fusion: dict[str, Any] = field(default_factory=dict)
    range_model: dict[str, Any] = field(default_factory=dict)
    pipeline: dict[str, Any] = field(default_factory=dict)
    log: dict[str, Any] = field(default_factory=dict)
    zenoh: dict[str, Any] = field(default_factory=dict)
    robot: dict[str, Any] = field(default_factory=dict)
    ros2: dict[str, Any] = field(default_factory=dict)
    text: str = ""  # the TOML as read, for the log
    warnings: tuple[str, ...] = ()  # "{file}: {key}: {what}", suspicious but not wrong

    @property
    def robot_name(self) -> str:
        """Who writes the logs and publishes: ``[robot] name``, else this machine's name."""
        return str(self.robot.get("name") or default_robot_name())

    @property
    def nav_frame_id(self) -> str:
        """The navigation frame's name in poses and transforms (ENU)."""
        return str(self.robot.get("nav_frame_id", "enu"))

    @property
    def body_frame_id(self) -> str:
        """The vehicle's frame's name (forward-left-up), child of the navigation frame."""
        return str(self.robot.get("body_frame_id", "base_link"))

    @property
    def ros2_settings(self) -> Ros2Settings:
        """The ``[ros2]`` section's names and domain (the domain from ``ROS_DOMAIN_ID`` when
        the section gives none)."""
        return settings_of(self.ros2)

    @property
    def zenoh_prefix(self) -> str:
        return str(self.zenoh.get("prefix") or f"uwbd/{self.robot_name}").strip("/")

    @property
    def aligner_wait_ns(self) -> int:
        return int(self.pipeline.get("aligner_wait_ms", ALIGNER_WAIT_MS) * 1_000_000)

    @property
    def pose_period_ns(self) -> int:
        return int(1e9 / self.pipeline.get("pose_rate_hz", POSE_RATE_HZ))

    @property
    def status_period_ns(self) -> int:
        return int(self.pipeline.get("status_period_s", STATUS_PERIOD_S) * 1e9)

    def intrinsics(self) -> ImuIntrinsics:
        """The ``[imu]`` intrinsics given, the others at their defaults (identity)."""
        given = self.imu_intrinsics
        return ImuIntrinsics(**{k: given[k] for k in IMU_INTRINSIC_KEYS[:-1] if k in given})

    def range_model_settings(self) -> RangeModel:
        """``[range_model]``: off (degree 0) unless given; checked by ``check_range_model``."""
        m = self.range_model
        degree = int(m.get("tag_degree", 0))
        delays = tuple(sorted((int(k, 0), float(v))
                              for k, v in m.get("anchor_delays_m", {}).items()))
        anchor_degree = int(m.get("anchor_degree", 0))
        return RangeModel(degree, tuple(float(c) for c in m["tag_coefficients_m"])
                          if degree else (),
                          tuple(vec3(row) for row in m.get("tag_mounting", IDENTITY3)), delays,
                          float(m.get("log_distance_m", 0.0)), anchor_degree,
                          tuple(float(c) for c in m["anchor_coefficients_m"])
                          if anchor_degree else (),
                          tuple(sorted(self.anchor_axes.items())))

    def filter_config(self) -> FilterConfig:
        """The filter's settings: each key given, the rest at :class:`FilterConfig`'s
        defaults (written there only)."""
        f = self.fusion
        given = {k: f[k] for k in _FILTER_KEYS if k in f}
        if "height_range_m" in f:
            given["height_range_m"] = (float(f["height_range_m"][0]),
                                       float(f["height_range_m"][1]))
        if "multipath_sigma_m" in f:  # 0 turns the states off
            given["multipath_states"] = f["multipath_sigma_m"] > 0
            given["multipath_sigma_m"] = f["multipath_sigma_m"] or FilterConfig.multipath_sigma_m
        gating = FilterConfig().gating
        return FilterConfig(
            mode=Mode(f.get("mode", FilterConfig.mode.value)), anchors_m=self.anchors_m,
            mounting_rotation=self.mounting, lever_arm_m=self.lever_arm_m,
            imu_noise=ImuNoise(**{IMU_NOISE_KEYS[k]: v for k, v in self.imu_noise.items()}),
            imu_limits=ImuLimits(
                acc_full_scale_mps2=self.imu_limits.get("acc_full_scale_mps2",
                                                        ImuLimits.acc_full_scale_mps2),
                gyro_full_scale_rps=self.imu_limits.get("gyro_full_scale_rps",
                                                        ImuLimits.gyro_full_scale_rps)),
            imu_intrinsics=self.intrinsics(),
            gravity_mps2=self.imu_intrinsics.get("gravity_mps2", GRAVITY_MPS2),
            robust=RobustPolicy.of_onset(f.get("robust", RobustPolicy.enabled),
                                         f.get("nlos_onset_m"),
                                         f.get("range_sigma_m", FilterConfig.range_sigma_m)),
            range_model=self.range_model_settings(),
            gating=GatingPolicy(min_anchors=f.get("min_anchors", gating.min_anchors),
                                max_range_m=f.get("max_range_m", gating.max_range_m)),
            health=HealthLimits(**{k: f[k] for k in _HEALTH_KEYS if k in f}),
            pose_period_ns=self.pose_period_ns,
            **given,
        )
