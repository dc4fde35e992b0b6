"""The simulator: a vehicle trajectory, its IMU, and its ranges to anchors, with ground truth.

Motion is commanded per segment (forward speed, yaw rate, climb rate), each command reached
with a smoothstep over ``blend_s`` so accelerations stay continuous. The body stays level
(roll = pitch = 0), heading follows the yaw rate, navigation frame ENU, body FLU. Truth is
integrated at 1 kHz; the IMU is derived from the same analytic accelerations, so IMU and
truth agree to integration error (< 1 mm over a run).

Sensors: IMU at ``imu_rate_hz`` in the sensor axes of ``mounting`` (default z-down: x
forward, y right, z down), with constant biases and white noise; ranges from the antenna
(lever arm) to each anchor at ``uwb_rate_hz`` with white noise, a constant per-anchor bias,
NLOS bursts (a positive extra delay for a while) and random dropouts. Everything is drawn
from one seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.fusion.rotation import Array

GRAVITY_MPS2 = 9.80665
DEFAULT_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (-5.0, 30.0, 0.0), (-5.0, -30.0, 0.0), (10.0, 10.0, 5.0),
    (10.0, -10.0, 5.0), (20.0, 30.0, 0.0), (20.0, -30.0, 0.0),
)
Z_DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))  # sensor -> body FLU
EPOCH_NS = 1_700_000_000 * 10**9  # simulated runs start at 2023-11-14T22:13:20Z

# (duration s, forward speed m/s, yaw rate rad/s, climb rate m/s)
DEFAULT_SEGMENTS: tuple[tuple[float, float, float, float], ...] = (
    (6.0, 0.0, 0.0, 0.0),  # still start
    (7.0, 1.5, 0.0, 0.0),  # straight
    (5.2, 1.5, 0.3, 0.0),  # left turn, ~90 deg
    (5.0, 1.5, 0.0, 0.0),
    (3.0, 0.0, 0.0, 0.0),  # stop
    (6.0, 1.0, 0.0, 0.25),  # climb
    (5.2, 1.2, 0.3, 0.0),  # left turn
    (6.0, 1.5, 0.0, -0.25),  # descend
    (5.2, 1.2, 0.3, 0.0),  # left turn
    (6.0, 1.5, 0.0, 0.0),
    (4.0, 0.0, 0.0, 0.0),  # stop
)


@dataclass(frozen=True)
class SimConfig:
    segments: tuple[tuple[float, float, float, float], ...] = DEFAULT_SEGMENTS
    blend_s: float = 1.0
    start_m: tuple[float, float, float] = (0.0, -12.0, 0.5)
    start_yaw_rad: float = 0.0
    anchors_m: tuple[tuple[float, float, float], ...] = DEFAULT_ANCHORS_M
    mounting: tuple[tuple[float, float, float], ...] = Z_DOWN
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.1)
    imu_rate_hz: float = 200.0
    uwb_rate_hz: float = 10.0
    acc_noise_mps2: float = 0.03  # per sample
    gyro_noise_rps: float = 0.003  # per sample
    acc_bias_sigma_mps2: float = 0.05
    gyro_bias_sigma_rps: float = 0.005
    range_noise_m: float = 0.10
    range_bias_sigma_m: float = 0.03
    nlos_rate_hz: float = 0.01  # per anchor: bursts start this often
    nlos_duration_s: float = 1.5
    nlos_extra_m: tuple[float, float] = (0.3, 1.0)
    dropout_prob: float = 0.02
    seed: int = 0


def sensor_settings(cfg: SimConfig) -> tuple[dict[str, float], dict[str, float]]:
    """The simulated sensors' specs as config keys (``[imu]``, ``[fusion]``), as a user
    would enter them from the datasheets and the anchors' calibration: white-noise
    densities (σ per sample / √rate) and the spread of the anchors' range offsets. The
    biases are constant here, so the bias walks keep the defaults."""
    imu = {"acc_noise_mps2_rthz": cfg.acc_noise_mps2 / math.sqrt(cfg.imu_rate_hz),
           "gyro_noise_rps_rthz": cfg.gyro_noise_rps / math.sqrt(cfg.imu_rate_hz)}
    return imu, {"range_sigma_m": cfg.range_noise_m, "range_bias_sigma_m": cfg.range_bias_sigma_m}


@dataclass
class Simulation:
    """Frames (time-ordered per stream) and truth sampled at the IMU times."""

    config: SimConfig
    imu: list[ImuSample] = field(default_factory=list)
    uwb: list[UwbRanges] = field(default_factory=list)
    truth_t_ns: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    truth_p_m: Array = field(default_factory=lambda: np.zeros((0, 3)))
    truth_v_mps: Array = field(default_factory=lambda: np.zeros((0, 3)))
    truth_yaw_rad: Array = field(default_factory=lambda: np.zeros(0))
    acc_bias_mps2: Array = field(default_factory=lambda: np.zeros(3))
    gyro_bias_rps: Array = field(default_factory=lambda: np.zeros(3))
    range_bias_m: Array = field(default_factory=lambda: np.zeros(0))



def _commands(cfg: SimConfig, t: Array) -> tuple[Array, Array]:
    """Commanded (speed, yaw rate, climb rate) and their time derivatives at times ``t``."""
    values = np.zeros((len(t), 3))
    rates = np.zeros((len(t), 3))
    prev = np.zeros(3)
    start = 0.0
    for duration, *target in cfg.segments:
        tgt = np.array(target, dtype=float)
        u = np.clip((t - start) / cfg.blend_s, 0.0, 1.0)
        s = 3 * u**2 - 2 * u**3
        ds = np.where((u > 0) & (u < 1), (6 * u - 6 * u**2) / cfg.blend_s, 0.0)
        inside = t >= start
        values[inside] = (prev + np.outer(s, tgt - prev))[inside]
        rates[inside] = np.outer(ds, tgt - prev)[inside]
        prev, start = tgt, start + duration
    return values, rates


def simulate(cfg: SimConfig | None = None) -> Simulation:
    """Run the simulator (deterministic for a given config and seed)."""
    cfg = cfg or SimConfig()
    rng = np.random.default_rng(cfg.seed)
    total_s = sum(seg[0] for seg in cfg.segments)
    fine_hz = 1000.0
    t = np.arange(0.0, total_s, 1.0 / fine_hz)
    (cmd, dcmd) = _commands(cfg, t)
    speed, yaw_rate, climb = cmd.T
    dspeed, _, dclimb = dcmd.T
    dt = 1.0 / fine_hz
    yaw = cfg.start_yaw_rad + np.concatenate(([0.0], np.cumsum((yaw_rate[1:] + yaw_rate[:-1])
                                                              * dt / 2)))
    v = np.column_stack([speed * np.cos(yaw), speed * np.sin(yaw), climb])
    p = np.array(cfg.start_m) + np.vstack([np.zeros(3), np.cumsum((v[1:] + v[:-1]) * dt / 2,
                                                                  axis=0)])
    a = np.column_stack([dspeed * np.cos(yaw) - speed * yaw_rate * np.sin(yaw),
                         dspeed * np.sin(yaw) + speed * yaw_rate * np.cos(yaw), dclimb])

    sim = Simulation(cfg)
    sim.acc_bias_mps2 = rng.normal(0, cfg.acc_bias_sigma_mps2, 3)
    sim.gyro_bias_rps = rng.normal(0, cfg.gyro_bias_sigma_rps, 3)
    sim.range_bias_m = rng.normal(0, cfg.range_bias_sigma_m, len(cfg.anchors_m))
    C_sb = np.array(cfg.mounting).T  # body -> sensor

    step = round(fine_hz / cfg.imu_rate_hz)
    idx = np.arange(0, len(t), step)
    sim.truth_t_ns = EPOCH_NS + np.round(t[idx] * 1e9).astype(np.int64)
    sim.truth_p_m, sim.truth_v_mps, sim.truth_yaw_rad = p[idx], v[idx], yaw[idx]
    c, s = np.cos(yaw[idx]), np.sin(yaw[idx])
    f_n = a[idx] + np.array([0.0, 0.0, GRAVITY_MPS2])
    f_b = np.column_stack([c * f_n[:, 0] + s * f_n[:, 1], -s * f_n[:, 0] + c * f_n[:, 1],
                           f_n[:, 2]])
    w_b = np.column_stack([np.zeros(len(idx)), np.zeros(len(idx)), yaw_rate[idx]])
    acc_s = (f_b @ C_sb.T) + sim.acc_bias_mps2 + rng.normal(0, cfg.acc_noise_mps2, f_b.shape)
    gyro_s = (w_b @ C_sb.T) + sim.gyro_bias_rps + rng.normal(0, cfg.gyro_noise_rps, w_b.shape)
    sim.imu = [ImuSample(int(tn), (float(f[0]), float(f[1]), float(f[2])),
                         (float(g[0]), float(g[1]), float(g[2])), 25.0)
               for tn, f, g in zip(sim.truth_t_ns, acc_s, gyro_s, strict=True)]

    anchors = np.array(cfg.anchors_m)
    lever = np.array(cfg.lever_arm_m)
    uwb_step = round(fine_hz / cfg.uwb_rate_hz)
    nlos_until = np.full(len(anchors), -1.0)
    nlos_extra = np.zeros(len(anchors))
    for k in range(0, len(t), uwb_step):
        tk = t[k]
        started = rng.random(len(anchors)) < cfg.nlos_rate_hz / cfg.uwb_rate_hz
        for i in np.flatnonzero(started & (nlos_until < tk)):
            nlos_until[i] = tk + cfg.nlos_duration_s
            nlos_extra[i] = rng.uniform(*cfg.nlos_extra_m)
        p_ant = p[k] + np.array([[math.cos(yaw[k]), -math.sin(yaw[k]), 0],
                                 [math.sin(yaw[k]), math.cos(yaw[k]), 0], [0, 0, 1]]) @ lever
        d = np.linalg.norm(anchors - p_ant, axis=1) + sim.range_bias_m
        d += rng.normal(0, cfg.range_noise_m, len(anchors))
        d += np.where(nlos_until >= tk, nlos_extra, 0.0)
        keep = rng.random(len(anchors)) >= cfg.dropout_prob
        ranges = tuple(AnchorRange(int(i), float(d[i])) for i in np.flatnonzero(keep))
        sim.uwb.append(UwbRanges(EPOCH_NS + round(tk * 1e9), ranges))
    return sim
