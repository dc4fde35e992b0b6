"""What the filter is told: its mode and every setting, with units in names (the TOML
configuration's ``[imu]`` and ``[fusion]`` keys land here through :mod:`uwbd.config`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

from uwbd.fusion.checks.gating import GatingPolicy
from uwbd.fusion.checks.imu_check import ImuLimits
from uwbd.fusion.checks.intrinsics import ImuIntrinsics
from uwbd.fusion.core.noise import GRAVITY_MPS2, ImuNoise
from uwbd.fusion.core.weights import RowPolicy
from uwbd.fusion.models.range_model import RangeModel

Vec3 = tuple[float, float, float]
IDENTITY3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
Z_DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))  # an IMU mounted upside down


@dataclass(frozen=True)
class HealthLimits:
    coast_after_s: float = 1.0
    range_timeout_s: float = 5.0
    # a pose is healthy only while its protection levels, at this risk, are within these
    integrity_risk: float = 1e-3
    horizontal_alert_limit_m: float = 0.5
    vertical_alert_limit_m: float = 1.0
    # a robot that needs no height (a ground robot) is healthy by the horizontal alone
    height_needed: bool = True
    # each range's unmodelled bias at most (ARAIM's nominal bias): antenna patterns, delays
    range_bias_bound_m: float = 0.05
    # the solution-separation test's false alerts, shared over the anchors, per test
    false_alert_probability: float = 1e-4
    window_count: int = 12  # innovations judged over the last this many UWB measurements
    max_rejected_fraction: float = 0.5
    max_mean_nis: float = 6.0  # of the window's NIS, each clipped at 25
    diverged_after_s: float = 2.0  # inconsistent this long: the state may be wrong
    recover_hold_s: float = 3.0
    imu_fault_hold_s: float = 1.0
    clear_hold_s: float = 0.5  # after the last fault, degraded this long still (hysteresis)


@dataclass(frozen=True)
class RestLimits:
    acc_std_mps2: float = 0.15  # |std of the specific force| over the window
    gyro_rps: float = 0.03  # |mean rate| and |std of the rate|
    gravity_tolerance_mps2: float = 1.0  # | |mean f| − g |: scale errors of a few % only


@dataclass(frozen=True)
class RobustPolicy:
    enabled: bool = True
    c_long: float = 2.5
    c_short: float = 4.0

    @staticmethod
    def of_onset(enabled: bool, nlos_onset_m: float | None, range_sigma_m: float
                 ) -> RobustPolicy:
        """The policy of a config: ``[fusion] nlos_onset_m`` (``uwbd calibrate-ranges``
        fits it: where a longer range becomes likelier NLOS than noise) as the long side's
        scale in the ranges' σ; without it, the default 2.5 σ."""
        if nlos_onset_m is None:
            return RobustPolicy(enabled)
        return RobustPolicy(enabled, c_long=nlos_onset_m / range_sigma_m)

    def rows(self, kinds: bytes, gate_1: float, fix_ok: bool) -> RowPolicy:
        """The numbers one update's rows are weighed with (:mod:`uwbd.fusion.core.weights`)."""
        return RowPolicy(kinds, gate_1, self.enabled, self.c_long, self.c_short, fix_ok)


class Mode(str, Enum):
    LOOSE = "loose"  # UWB least-squares positions are the measurements
    TIGHT = "tight"  # every range is a scalar measurement


@dataclass(frozen=True)
class FilterConfig:
    """Everything the filter is told. Units in names; rotations as row-major 3×3 tuples."""

    mode: Mode = Mode.TIGHT
    anchors_m: Mapping[int, Vec3] = field(default_factory=dict)
    mounting_rotation: tuple[Vec3, Vec3, Vec3] = IDENTITY3  # C_bs: sensor axes -> body FLU
    lever_arm_m: Vec3 = (0.0, 0.0, 0.0)  # IMU -> UWB antenna, body axes
    # > 0: the lever arm's error as three states with this prior σ per axis (0: as given)
    lever_arm_sigma_m: float = 0.0
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    imu_limits: ImuLimits = field(default_factory=ImuLimits)
    # scale, offsets (and a gyro dead-band) per sensor axis, applied before the mounting
    imu_intrinsics: ImuIntrinsics = field(default_factory=ImuIntrinsics)
    gravity_mps2: float = GRAVITY_MPS2  # local gravity: INS, start at rest, rest test
    range_sigma_m: float = 0.10
    acc_bias_sigma_mps2: float = 0.1  # initial; the vertical part is set from |f| - g at rest
    gate_probability: float = 0.997  # per-measurement χ² gate (3 σ for a scalar)
    gating: GatingPolicy = field(default_factory=lambda: GatingPolicy(min_anchors=1))
    robust: RobustPolicy = field(default_factory=RobustPolicy)
    range_bias_states: bool = True  # self-calibrate each anchor's antenna delay
    range_bias_sigma_m: float = 0.1  # each anchor's own antenna delay, as a range offset
    tag_delay_sigma_m: float = 0.2  # the tag's antenna delay: one offset common to all ranges
    # one Gauss–Markov range error per anchor: multipath and antenna patterns make real range
    # errors time-correlated (seconds); off for white range noise (a simulator's)
    multipath_states: bool = True
    multipath_sigma_m: float = 0.07
    multipath_tau_s: float = 1.0
    # the tag antenna's direction-dependent delay (models.range_model): off unless calibrated
    range_model: RangeModel = field(default_factory=RangeModel)
    tag_side: str = "auto"  # of a plane of anchors: auto | below | above (see .mirror)
    height_range_m: tuple[float, float] | None = None  # where the tag can be (a hint)
    zupt: bool = True
    zupt_sigma_mps: float = 0.02
    zupt_max_speed_mps: float = 0.15
    nhc: bool = False
    nhc_sigma_mps: float = 0.1
    known_height_m: float | None = None
    height_sigma_m: float = 0.05
    static_window_s: float = 0.5
    rest: RestLimits = field(default_factory=RestLimits)
    init_static_s: float = 1.0
    init_max_wait_s: float = 3.0
    range_window_s: float = 0.2  # single ranges solved together for a fix (see .fixes)
    fix_interval_s: float = 0.1
    max_imu_gap_s: float = 0.5
    # the policy (health, installation checks, exclusion, recovery) runs with every epoch and,
    # for single ranges while tracking, once a pose period ([pipeline] pose_rate_hz; ten
    # times a second at least)
    pose_period_ns: int = 20_000_000
    attitude_lost_after_s: float = 3.0  # an IMU gap or rejected burst this long: re-level
    health: HealthLimits = field(default_factory=HealthLimits)
    align_window_s: float = 2.0  # coarse heading alignment: window of UWB fixes compared
    align_min_dv_mps: float = 0.5  # ... with this much horizontal velocity change at least
