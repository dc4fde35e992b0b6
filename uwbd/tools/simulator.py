"""The simulator: a vehicle trajectory, its IMU, and its ranges to anchors, with ground truth.

Motion is commanded per segment (forward speed, yaw rate, climb rate), each command reached
with a smoothstep over ``blend_s`` so accelerations stay continuous. The body stays level
(roll = pitch = 0), heading follows the yaw rate, navigation frame ENU, body FLU. Truth is
integrated at 1 kHz; the IMU is derived from the same analytic accelerations, so IMU and
truth agree to integration error (< 1 mm over a run).

Sensors: IMU at ``imu_rate_hz`` in the sensor axes of ``mounting`` (default z-down: x
forward, y right, z down), with constant biases and white noise, clipped at the full scale;
ranges from the antenna (lever arm) to each anchor with white noise, a constant per-anchor
bias, NLOS bursts (a positive extra delay for a while) and random dropouts. Everything is
drawn from one seeded generator.

UWB schedules: ``"epoch"`` (default) sends all anchors' ranges in one message at
``uwb_rate_hz``; ``"round_robin"`` sends one range per message, the anchors polled in turn,
``uwb_rate_hz`` being the total range rate, each time jittered by up to ``uwb_jitter_s``.

Faults, all off by default, windows as (start s, duration s) from the run's start, a window
covering start <= t < start + duration: ``anchor_outages_s`` (one anchor sends nothing),
``uwb_outages_s`` (no UWB message), ``imu_gaps_s`` (no IMU sample), ``imu_saturations_s``
(every sample pinned at +full scale on every sensor axis), and ``imu_spikes_s`` (the IMU
sample nearest each time gets ``imu_spike_acc_mps2`` / ``imu_spike_gyro_rps`` added). The
faults take no draws from the generator, so a run with faults is the run without them,
with the faulted parts changed or removed. Truth stays at the nominal IMU times throughout.

IMU intrinsic errors, off by default (and then not computed at all, so every run stays bit
for bit): ``acc_scale`` and ``acc_offset_mps2`` per sensor axis (a reading is ``scale ·
true + offset``, then the random bias and the noise), ``gyro_offset_rps``. A six-position
static capture for ``uwbd calibrate-imu`` (each axis up and down in turn, hand-turned between
the holds, each hold tipped a little) comes from :func:`six_position_capture`.

Presets (functions of the seed returning a :class:`SimConfig`): :func:`seed_layout`,
:func:`ceiling_room`, :func:`handheld_async`; all in ``PRESETS``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.settings import Z_DOWN  # sensor -> body FLU: an IMU mounted upside down

GRAVITY_MPS2 = 9.80665
DEFAULT_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (-5.0, 30.0, 0.0), (-5.0, -30.0, 0.0), (10.0, 10.0, 5.0),
    (10.0, -10.0, 5.0), (20.0, 30.0, 0.0), (20.0, -30.0, 0.0),
)
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
    tag_delay_sigma_m: float = 0.0  # one offset common to every range (the tag's delay)
    ground_vehicle: bool = False  # no sideways or vertical body velocity: NHC holds
    nlos_rate_hz: float = 0.01  # per anchor: bursts start this often
    nlos_duration_s: float = 1.5
    nlos_extra_m: tuple[float, float] = (0.3, 1.0)
    dropout_prob: float = 0.02
    seed: int = 0
    # UWB schedule: "epoch" (all anchors in one message at uwb_rate_hz) or "round_robin"
    # (one range a message, anchors in turn, uwb_rate_hz the total rate, times jittered)
    uwb_schedule: str = "epoch"
    uwb_jitter_s: float = 0.001  # round_robin: each time moved by U(-j, +j)
    anchor_nlos_rate_hz: tuple[float, ...] = ()  # per anchor; empty: nlos_rate_hz for all
    # faults, windows (start s, duration s) from the run's start
    anchor_outages_s: tuple[tuple[int, float, float], ...] = ()  # (anchor index, start, dur)
    uwb_outages_s: tuple[tuple[float, float], ...] = ()
    nlos_all_s: tuple[tuple[float, float], ...] = ()  # every anchor NLOS (epochs), each by
    nlos_all_extra_m: tuple[float, float] = (0.5, 2.0)  # its own U(lo, hi), a window long
    imu_gaps_s: tuple[tuple[float, float], ...] = ()
    imu_saturations_s: tuple[tuple[float, float], ...] = ()
    imu_spikes_s: tuple[float, ...] = ()  # the sample nearest each time is corrupted
    imu_spike_acc_mps2: tuple[float, float, float] = (100.0, 0.0, 0.0)  # added, sensor axes
    imu_spike_gyro_rps: tuple[float, float, float] = (0.0, 0.0, 20.0)
    acc_full_scale_mps2: float = 16 * GRAVITY_MPS2
    gyro_full_scale_rps: float = math.radians(2000)
    # IMU intrinsic errors per sensor axis (what ``uwbd calibrate-imu`` finds): each reading
    # is acc_scale · true + acc_offset_mps2 (+ the random bias, + noise); gyro + offset.
    # At the defaults nothing is computed: runs without them stay bit for bit as they were
    acc_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    acc_offset_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_offset_rps: tuple[float, float, float] = (0.0, 0.0, 0.0)


def sensor_settings(cfg: SimConfig) -> tuple[dict[str, float], dict[str, float | bool]]:
    """The simulated sensors' specs as config keys (``[imu]``, ``[fusion]``), as a user
    would enter them from the datasheets and the anchors' calibration: white-noise
    densities (σ per sample / √rate), the spread of the anchors' range offsets and of the
    tag's delay, no time-correlated range error (the simulated range noise is white; NLOS
    bursts aside), and, for a ground vehicle, the non-holonomic constraint.
    The biases are constant here, so the bias walks keep the defaults."""
    imu = {"acc_noise_mps2_rthz": cfg.acc_noise_mps2 / math.sqrt(cfg.imu_rate_hz),
           "gyro_noise_rps_rthz": cfg.gyro_noise_rps / math.sqrt(cfg.imu_rate_hz)}
    fusion: dict[str, float | bool] = {
        "range_sigma_m": cfg.range_noise_m, "range_bias_sigma_m": cfg.range_bias_sigma_m,
        "tag_delay_sigma_m": cfg.tag_delay_sigma_m, "multipath_sigma_m": 0.0}
    if cfg.ground_vehicle:
        fusion["nhc"] = True
    return imu, fusion


@dataclass
class Simulation:
    """Frames (time-ordered per stream) and truth sampled at the nominal IMU times (also
    through IMU gaps)."""

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


def _in_windows(t: Array, windows: tuple[tuple[float, float], ...]) -> npt.NDArray[np.bool_]:
    """Which times lie in one of the (start, duration) windows: start <= t < start + duration."""
    inside = np.zeros(np.shape(t), dtype=bool)
    for start, duration in windows:
        inside |= (t >= start) & (t < start + duration)
    return inside


def _check(cfg: SimConfig, total_s: float) -> None:
    if cfg.uwb_schedule not in ("epoch", "round_robin"):
        raise ValueError(f"uwb_schedule must be 'epoch' or 'round_robin', "
                         f"got {cfg.uwb_schedule!r}")
    n = len(cfg.anchors_m)
    if cfg.anchor_nlos_rate_hz and len(cfg.anchor_nlos_rate_hz) != n:
        raise ValueError(f"anchor_nlos_rate_hz: {len(cfg.anchor_nlos_rate_hz)} rates "
                         f"for {n} anchors")
    for i, _, _ in cfg.anchor_outages_s:
        if not 0 <= i < n:
            raise ValueError(f"anchor_outages_s: no anchor {i} (there are {n})")
    if cfg.uwb_schedule == "round_robin" and not 0 <= 2 * cfg.uwb_jitter_s < 1 / cfg.uwb_rate_hz:
        raise ValueError(f"uwb_jitter_s {cfg.uwb_jitter_s} must be under half the "
                         f"{1 / cfg.uwb_rate_hz:.4f} s between ranges")
    for ts in cfg.imu_spikes_s:
        if not 0 <= ts <= total_s:
            raise ValueError(f"imu_spikes_s: {ts} s is outside the {total_s} s run")


def simulate(cfg: SimConfig | None = None) -> Simulation:
    """Run the simulator (deterministic for a given config and seed)."""
    cfg = cfg or SimConfig()
    rng = np.random.default_rng(cfg.seed)
    total_s = sum(seg[0] for seg in cfg.segments)
    _check(cfg, total_s)
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
    if cfg.tag_delay_sigma_m > 0:  # drawn only then: runs without one stay as they were
        sim.range_bias_m += rng.normal(0, cfg.tag_delay_sigma_m)
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
    f_s = f_b @ C_sb.T
    acc_s = f_s + sim.acc_bias_mps2 + rng.normal(0, cfg.acc_noise_mps2, f_b.shape)
    gyro_s = (w_b @ C_sb.T) + sim.gyro_bias_rps + rng.normal(0, cfg.gyro_noise_rps, w_b.shape)
    _intrinsic_errors(cfg, f_s, acc_s, gyro_s)
    kept = _imu_faults(cfg, t[idx], acc_s, gyro_s)
    sim.imu = [ImuSample(int(tn), (float(f[0]), float(f[1]), float(f[2])),
                         (float(g[0]), float(g[1]), float(g[2])), 25.0)
               for tn, f, g in zip(sim.truth_t_ns[kept], acc_s[kept], gyro_s[kept],
                                   strict=True)]
    if cfg.uwb_schedule == "round_robin":
        sim.uwb = _round_robin(cfg, rng, t, p, yaw, sim.range_bias_m)
    else:
        sim.uwb = _epochs(cfg, rng, t, p, yaw, sim.range_bias_m)
    return sim


def _intrinsic_errors(cfg: SimConfig, f_s: Array, acc: Array, gyro: Array) -> None:
    """Add the intrinsic errors in place (``f_s``: the true specific force, sensor axes):
    ``(scale − 1) · f`` and the offsets; nothing at all at their defaults."""
    if cfg.acc_scale != (1.0, 1.0, 1.0):
        acc += f_s * (np.array(cfg.acc_scale) - 1.0)
    if cfg.acc_offset_mps2 != (0.0, 0.0, 0.0):
        acc += np.array(cfg.acc_offset_mps2)
    if cfg.gyro_offset_rps != (0.0, 0.0, 0.0):
        gyro += np.array(cfg.gyro_offset_rps)


def _imu_faults(cfg: SimConfig, t_s: Array, acc: Array, gyro: Array
                ) -> npt.NDArray[np.bool_]:
    """Apply the IMU faults in place (spikes, then saturations, then the full-scale clip);
    return which samples are sent (not in a gap)."""
    kept = ~_in_windows(t_s, cfg.imu_gaps_s)
    if cfg.imu_spikes_s:
        sent = np.flatnonzero(kept)
        nearest = [sent[np.argmin(np.abs(t_s[sent] - ts))] for ts in cfg.imu_spikes_s]
        for k in np.unique(nearest):
            acc[k] += cfg.imu_spike_acc_mps2
            gyro[k] += cfg.imu_spike_gyro_rps
    saturated = _in_windows(t_s, cfg.imu_saturations_s)
    acc[saturated] = cfg.acc_full_scale_mps2
    gyro[saturated] = cfg.gyro_full_scale_rps
    np.clip(acc, -cfg.acc_full_scale_mps2, cfg.acc_full_scale_mps2, out=acc)
    np.clip(gyro, -cfg.gyro_full_scale_rps, cfg.gyro_full_scale_rps, out=gyro)
    return kept


def _antenna(cfg: SimConfig, p: Array, yaw: float) -> Array:
    lever = np.array(cfg.lever_arm_m)
    p_ant: Array = p + np.array([[math.cos(yaw), -math.sin(yaw), 0],
                                 [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]) @ lever
    return p_ant


def _nlos_rates(cfg: SimConfig) -> Array:
    if cfg.anchor_nlos_rate_hz:
        return np.array(cfg.anchor_nlos_rate_hz, dtype=float)
    return np.full(len(cfg.anchors_m), cfg.nlos_rate_hz)


def _anchor_out(cfg: SimConfig, i: int, tk: float) -> bool:
    return any(j == i and start <= tk < start + duration
               for j, start, duration in cfg.anchor_outages_s)


def _epochs(cfg: SimConfig, rng: np.random.Generator, t: Array, p: Array, yaw: Array,
            range_bias_m: Array) -> list[UwbRanges]:
    """All anchors' ranges in one message at ``uwb_rate_hz``, on the 1 kHz truth grid."""
    anchors = np.array(cfg.anchors_m)
    uwb_step = round(1000.0 / cfg.uwb_rate_hz)
    nlos_until = np.full(len(anchors), -1.0)
    nlos_extra = np.zeros(len(anchors))
    start_prob = (cfg.nlos_rate_hz / cfg.uwb_rate_hz if not cfg.anchor_nlos_rate_hz
                  else _nlos_rates(cfg) / cfg.uwb_rate_hz)
    # per window of nlos_all_s and anchor, its delay (a generator of its own: the rest of
    # the run is the same with or without); row 0: outside every window
    extra_rng = np.random.default_rng([cfg.seed, 7])
    all_nlos = np.vstack([np.zeros(len(anchors)), extra_rng.uniform(
        *cfg.nlos_all_extra_m, (len(cfg.nlos_all_s), len(anchors)))])
    out: list[UwbRanges] = []
    for k in range(0, len(t), uwb_step):
        tk = t[k]
        started = rng.random(len(anchors)) < start_prob
        for i in np.flatnonzero(started & (nlos_until < tk)):
            nlos_until[i] = tk + cfg.nlos_duration_s
            nlos_extra[i] = rng.uniform(*cfg.nlos_extra_m)
        p_ant = _antenna(cfg, p[k], yaw[k])
        d = np.linalg.norm(anchors - p_ant, axis=1) + range_bias_m
        d += rng.normal(0, cfg.range_noise_m, len(anchors))
        d += np.where(nlos_until >= tk, nlos_extra, 0.0)
        d += all_nlos[_window_index(tk, cfg.nlos_all_s)] if cfg.nlos_all_s else 0.0
        keep = rng.random(len(anchors)) >= cfg.dropout_prob
        if cfg.uwb_outages_s and _in_windows(np.array([tk]), cfg.uwb_outages_s)[0]:
            continue  # after the draws: an outage changes nothing else in the run
        ranges = tuple(AnchorRange(int(i), float(d[i])) for i in np.flatnonzero(keep)
                       if not _anchor_out(cfg, int(i), tk))
        out.append(UwbRanges(EPOCH_NS + round(tk * 1e9), ranges))
    return out


def _window_index(t_s: float, windows: tuple[tuple[float, float], ...]) -> int:
    """1 + the index of the window (start, duration) holding ``t_s``; 0 for none."""
    for k, (start, duration) in enumerate(windows):
        if start <= t_s < start + duration:
            return k + 1
    return 0


def _round_robin(cfg: SimConfig, rng: np.random.Generator, t: Array, p: Array, yaw: Array,
                 range_bias_m: Array) -> list[UwbRanges]:
    """One range a message, the anchors polled in turn at ``uwb_rate_hz`` in total, each
    time jittered; the range is the one at its (jittered) time. A dropped or outaged range
    sends no message."""
    anchors = np.array(cfg.anchors_m)
    n = len(anchors)
    period_s = 1.0 / cfg.uwb_rate_hz
    slots = np.arange(int(t[-1] / period_s))
    t_s = (slots + 0.5) * period_s + rng.uniform(-cfg.uwb_jitter_s, cfg.uwb_jitter_s,
                                                 len(slots))
    t_s = t_s[t_s <= t[-1]]
    ids = np.arange(len(t_s)) % n
    start_prob = _nlos_rates(cfg) * n / cfg.uwb_rate_hz  # per poll of that anchor
    started = rng.random(len(t_s)) < start_prob[ids]
    noise = rng.normal(0, cfg.range_noise_m, len(t_s))
    keep = rng.random(len(t_s)) >= cfg.dropout_prob
    nlos_until = np.full(n, -1.0)
    nlos_extra = np.zeros(n)
    extra = np.zeros(len(t_s))
    for j, (tj, a) in enumerate(zip(t_s, ids, strict=True)):
        if started[j] and nlos_until[a] < tj:
            nlos_until[a] = tj + cfg.nlos_duration_s
            nlos_extra[a] = rng.uniform(*cfg.nlos_extra_m)
        if nlos_until[a] >= tj:
            extra[j] = nlos_extra[a]
    p_t = np.column_stack([np.interp(t_s, t, p[:, k]) for k in range(3)])
    yaw_t = np.interp(t_s, t, yaw)
    keep &= ~_in_windows(t_s, cfg.uwb_outages_s)
    out: list[UwbRanges] = []
    for j in np.flatnonzero(keep).tolist():
        i = int(ids[j])
        if _anchor_out(cfg, i, float(t_s[j])):
            continue
        d = float(np.linalg.norm(anchors[i] - _antenna(cfg, p_t[j], float(yaw_t[j])))
                  + range_bias_m[i] + noise[j] + extra[j])
        out.append(UwbRanges(EPOCH_NS + round(float(t_s[j]) * 1e9), (AnchorRange(i, d),)))
    return out
