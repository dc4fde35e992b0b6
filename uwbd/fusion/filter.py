"""The fusion filter: frames in, poses and per-measurement reports out.

``Filter.predict(imu)``, ``Filter.update(uwb)``, ``Filter.pose()`` — pure and deterministic
(same frames in, same poses out). Policy lives here; the algebra in :mod:`uwbd.fusion.eskf`.

Life cycle:

1. **Waiting**: IMU samples (turned into body axes) and UWB least-squares fixes are collected.
   When the IMU has been at rest for ``init_static_s`` and fixes exist for that time, the
   filter starts from rest: gyro bias = mean gyro, roll and pitch from the mean specific
   force, position = mean fix, velocity 0. If the vehicle never rests within
   ``init_max_wait_s``, it starts **moving**: position from the latest fix, velocity from
   the fixes' slope, roll/pitch from the mean specific force, a larger gyro-bias variance,
   and the status says so.
2. **Running**: heading starts unknown (yaw σ = 180°) and is aligned by the ranges once the
   vehicle moves; ``heading_observable`` turns true when its σ falls below 10°.
3. **Recovery**: when most ranges keep failing the gate (NLOS, or a diverged state) for
   ``reinit_after_bad_epochs`` epochs, position and velocity are re-initialised from UWB
   least squares and the event is counted and reported.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from statistics import NormalDist
from typing import NamedTuple

import numpy as np

from drivers.frames import ImuSample, UwbRanges
from uwbd.fusion.alignment import HeadingAligner
from uwbd.fusion.eskf import GRAVITY_MPS2, N_CORE, P_, TH_, V_, Eskf, ImuNoise
from uwbd.fusion.gating import GatingCounters, GatingPolicy, gate
from uwbd.fusion.lsq import LsqFix, coplanar, multilaterate
from uwbd.fusion.rotation import Array, quat_from_euler, quat_to_matrix, skew
from uwbd.fusion.smoother import EpochRecord, Nominal
from uwbd.fusion.types import FusionReport, Pose

Vec3 = tuple[float, float, float]
HELD_YAW_SIGMA_RAD = 1e-3  # the heading's σ while it is held, before the coarse alignment
IDENTITY3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


class Rows(NamedTuple):
    """Measurement rows of one update: ``H`` (m×n), residuals ``y``, noise variances ``R``,
    and what each row is (kind, key) for its report."""

    H: Array
    y: Array
    R: Array
    keys: list[tuple[str, str]]

    @staticmethod
    def empty(n: int) -> Rows:
        return Rows(np.zeros((0, n)), np.zeros(0), np.zeros(0), [])

    @staticmethod
    def stack(parts: list[Rows]) -> Rows:
        parts = [r for r in parts if r.keys]
        if len(parts) <= 1:
            return parts[0] if parts else Rows.empty(0)
        return Rows(np.vstack([r.H for r in parts]), np.concatenate([r.y for r in parts]),
                    np.concatenate([r.R for r in parts]), [k for r in parts for k in r.keys])


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
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    range_sigma_m: float = 0.10
    acc_bias_sigma_mps2: float = 0.1  # initial; the vertical part is set from |f| - g at rest
    gate_probability: float = 0.997  # per-measurement χ² gate (3 σ for a scalar)
    gating: GatingPolicy = field(default_factory=lambda: GatingPolicy(min_anchors=1))
    range_bias_states: bool = True  # self-calibrate each anchor's antenna delay
    range_bias_sigma_m: float = 0.1  # each anchor's own antenna delay, as a range offset
    tag_delay_sigma_m: float = 0.2  # the tag's antenna delay: one offset common to all ranges
    zupt: bool = True
    zupt_sigma_mps: float = 0.02
    zupt_max_speed_mps: float = 0.3
    nhc: bool = False
    nhc_sigma_mps: float = 0.1
    known_height_m: float | None = None
    height_sigma_m: float = 0.05
    static_window_s: float = 0.5
    static_acc_std_mps2: float = 0.15
    static_gyro_rps: float = 0.03
    init_static_s: float = 1.0
    init_max_wait_s: float = 3.0
    max_imu_gap_s: float = 0.5
    reinit_after_bad_epochs: int = 20
    align_window_s: float = 2.0  # coarse heading alignment: window of UWB fixes compared
    align_min_dv_mps: float = 0.8  # ... with this much horizontal velocity change at least


class Filter:
    """Loosely or tightly coupled UWB/INS error-state EKF (see module doc)."""

    def __init__(self, config: FilterConfig, record: bool = False) -> None:
        """``record``: keep every epoch's prior and posterior for :mod:`.smoother` (offline;
        about 13 kB an epoch with 8 anchors)."""
        self.cfg = config
        self.records: list[EpochRecord] | None = [] if record else None
        self._coasted = False
        self.C_bs = np.array(config.mounting_rotation, dtype=float)
        if not np.allclose(self.C_bs @ self.C_bs.T, np.eye(3), atol=1e-6) or \
                np.linalg.det(self.C_bs) < 0:
            raise ValueError("mounting_rotation must be a proper rotation matrix")
        self._C = tuple(tuple(float(x) for x in row) for row in self.C_bs)
        self.lever = np.array(config.lever_arm_m, dtype=float)
        self.ekf: Eskf | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.gating = GatingCounters()
        self.status = "waiting for data"
        self.t_ns: int | None = None  # time of the nominal state
        self._imu_t_ns: int | None = None
        self._last_imu: tuple[Vec3, Vec3] | None = None
        # (t_ns, acc xyz, gyro xyz) in body axes over the last window_ns: rest detection
        self._window: collections.deque[tuple[float, ...]] = collections.deque()
        self._window_ns = int(max(config.static_window_s, config.init_static_s) * 1e9)
        self._fixes: collections.deque[tuple[int, Array]] = collections.deque(maxlen=100)
        self._first_t_ns: int | None = None
        self._bad_epochs = 0
        self._aligner = HeadingAligner(config.align_window_s, config.align_min_dv_mps,
                                       config.range_sigma_m)
        self._aligned = False
        self._bias_index: dict[int, int] = {}
        if config.range_bias_states and config.mode is Mode.TIGHT:  # unobservable in loose
            self._bias_index = {a: N_CORE + i for i, a in enumerate(sorted(config.anchors_m))}
        self._gate_1 = chi2_quantile(config.gate_probability, 1)
        self._gate_3 = chi2_quantile(config.gate_probability, 3)
        anchors = np.array(list(config.anchors_m.values())) if config.anchors_m else None
        self._fixed_z = (config.known_height_m if anchors is not None and coplanar(anchors)
                         else None)

    # -- inputs ---------------------------------------------------------------------------
    def predict(self, imu: ImuSample) -> None:
        """Integrate one IMU sample (sensor axes); bad samples are counted, never used."""
        a, g = imu.acc_mps2, imu.gyro_rps
        if not math.isfinite(a[0] + a[1] + a[2] + g[0] + g[1] + g[2]):  # NaN and inf propagate
            self.counters["imu_not_finite"] += 1
            return
        acc, gyro = self._to_body(a), self._to_body(g)
        if self._first_t_ns is None:
            self._first_t_ns = imu.t_ns
        prev = self._imu_t_ns
        if prev is not None and imu.t_ns <= prev:
            self.counters["imu_out_of_order"] += 1
            return
        gap = prev is not None and (imu.t_ns - prev) / 1e9 > self.cfg.max_imu_gap_s
        self._imu_t_ns = imu.t_ns
        self._remember(imu.t_ns, acc, gyro)
        if self.ekf is None:
            self._last_imu = (acc, gyro)
            return
        assert self.t_ns is not None
        dt = (imu.t_ns - self.t_ns) / 1e9
        if gap:
            self.counters["imu_gaps"] += 1  # coasted through by _predict_to; resume here
            self._coasted = True
        elif dt > 0:
            self.ekf.predict(acc, gyro, dt)
        self.t_ns = imu.t_ns
        self._last_imu = (acc, gyro)

    def update(self, uwb: UwbRanges) -> list[FusionReport]:
        """Fuse one ranging epoch; returns one report per measurement (accepted or not)."""
        if self._first_t_ns is None:
            self._first_t_ns = uwb.t_ns
        result = gate(uwb, self.cfg.gating, self.gating)
        reports = [FusionReport(uwb.t_ns, "range", str(r.anchor_id), math.nan, math.nan,
                                math.nan, False, why.value) for r, why in result.rejected]
        if result.epoch is None:
            return reports
        ids, anchors, ranges = self._resolve(result.epoch, reports)
        if len(ids) == 0:
            return reports
        # the least-squares fix is needed to start, in loose mode, and to recover
        fix = None
        if self.ekf is None or self.cfg.mode is Mode.LOOSE:
            fix = self._lsq(anchors, ranges)
            if fix is not None:
                self._fixes.append((uwb.t_ns, fix.position_m))
        if self.ekf is None:
            self._try_initialise(uwb.t_ns, fix)
            if self.ekf is not None:
                self._update_status()
            return reports
        if self.t_ns is not None and uwb.t_ns < self.t_ns:
            self.counters["uwb_late"] += 1  # older than the state: the aligner's job
            return reports
        self._predict_to(uwb.t_ns)
        dv = self.ekf.interval_dv_n()  # read before propagate() starts a new interval
        self.ekf.propagate()
        # the smoother can step back from this epoch over a plain Kalman prediction only
        linked = self._aligned and not self._coasted
        self._coasted = False
        if not self._aligned:
            self._aligner.add_ins_dv(dv)
            # the heading is unknown: the INS's horizontal Δv may point anywhere; for a heading
            # error uniform over ±180° the RMS error of a turned Δv is √2 |Δv|, so the fixes
            # must be free to say where it went
            extra = 2.0 * (dv[0] ** 2 + dv[1] ** 2)
            self.ekf.P[3, 3] += extra
            self.ekf.P[4, 4] += extra
            self._align_heading(uwb.t_ns, fix, anchors, ranges)
        rows = Rows.stack([self._measurement_rows(ids, anchors, ranges, fix),
                           *self._constraints()])
        prior = self._snapshot() if self.records is not None else None
        reports += self._fuse(uwb.t_ns, rows)
        if self._needs_recovery(reports):
            self._recover(fix or self._lsq(anchors, ranges))
            linked = False
        if prior is not None and self.records is not None:
            Phi = np.eye(self.ekf.n)
            Phi[:N_CORE, :N_CORE] = self.ekf.last_Phi
            self.records.append(EpochRecord(uwb.t_ns, *prior, *self._snapshot(),
                                            Phi if linked else None))
        self._update_status()
        return reports

    # -- outputs --------------------------------------------------------------------------
    def pose(self) -> Pose | None:
        ekf = self.ekf
        if ekf is None or self.t_ns is None:
            return None
        R = ekf.R
        cov = np.zeros((6, 6))
        cov[:3, :3] = ekf.P[P_, P_]
        cov[:3, 3:] = ekf.P[P_, TH_] @ R.T
        cov[3:, :3] = cov[:3, 3:].T
        cov[3:, 3:] = R @ ekf.P[TH_, TH_] @ R.T
        w, x, y, z = ekf.q
        return Pose(
            t_ns=self.t_ns, position_m=(ekf.p[0], ekf.p[1], ekf.p[2]),
            velocity_mps=(ekf.v[0], ekf.v[1], ekf.v[2]), orientation_xyzw=(x, y, z, w),
            covariance=tuple(cov.ravel().tolist()), status=self.status,
            heading_observable=self._aligned and ekf.yaw_sigma_rad() < math.radians(10),
        )

    # -- internals ------------------------------------------------------------------------
    def _snapshot(self) -> tuple[Nominal, Array]:
        ekf = self.ekf
        assert ekf is not None
        return (Nominal(np.array(ekf.p), np.array(ekf.v), np.array(ekf.q), np.array(ekf.b_g),
                        np.array(ekf.b_a), ekf.b_r.copy()), ekf.P.copy())

    def _to_body(self, v: tuple[float, float, float]) -> Vec3:
        """``C_bs v`` in plain floats: this runs for every IMU sample."""
        (a, b, c), (d, e, f), (g, h, i) = self._C
        x, y, z = v
        return (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z)

    def _remember(self, t_ns: int, acc: Vec3, gyro: Vec3) -> None:
        window = self._window
        window.append((t_ns, *acc, *gyro))
        oldest_ns = t_ns - self._window_ns
        while window[0][0] < oldest_ns:
            window.popleft()

    def _static(self, span_s: float) -> bool:
        """At rest over the last ``span_s``: specific force steady and rotation small."""
        if not self._window:
            return False
        t_end = self._window[-1][0]
        if (t_end - self._window[0][0]) < 0.9 * span_s * 1e9:
            return False
        samples = np.array(self._window)
        recent = samples[samples[:, 0] >= t_end - span_s * 1e9]
        if len(recent) < 3:
            return False
        acc, gyro = recent[:, 1:4], recent[:, 4:7]
        return bool(np.linalg.norm(acc.std(axis=0)) < self.cfg.static_acc_std_mps2
                    and np.linalg.norm(gyro.mean(axis=0)) < self.cfg.static_gyro_rps
                    and np.linalg.norm(gyro.std(axis=0)) < self.cfg.static_gyro_rps)

    def _resolve(self, epoch: UwbRanges, reports: list[FusionReport]
                 ) -> tuple[list[int], Array, Array]:
        """Anchor positions for each range: configured first, else as the device sends."""
        ids, anchors, ranges = [], [], []
        for r in epoch.ranges:
            pos = self.cfg.anchors_m.get(r.anchor_id, r.anchor_position_m)
            if pos is None:
                self.gating.rejections["unknown_anchor"] += 1
                reports.append(FusionReport(epoch.t_ns, "range", str(r.anchor_id), math.nan,
                                            math.nan, math.nan, False, "unknown_anchor"))
                continue
            ids.append(r.anchor_id)
            anchors.append(pos)
            ranges.append(r.range_m)
        return ids, np.array(anchors, dtype=float).reshape(-1, 3), np.array(ranges)

    def _lsq(self, anchors: Array, ranges: Array) -> LsqFix | None:
        x0 = None
        if self.ekf is not None:
            x0 = np.array(self.ekf.p) + self.ekf.R @ self.lever
        elif self._fixes:
            x0 = self._fixes[-1][1]
        return multilaterate(anchors, ranges, self.cfg.range_sigma_m, x0, self._fixed_z)

    def _try_initialise(self, t_ns: int, fix: LsqFix | None) -> None:
        if fix is None or not self._window:
            return
        cfg = self.cfg
        waited_s = (t_ns - (self._first_t_ns or t_ns)) / 1e9
        means = np.mean(self._window, axis=0)
        acc, gyro = means[1:4], means[4:7]
        recent = [p for t, p in self._fixes if t >= t_ns - cfg.init_static_s * 1e9]
        roll = math.atan2(acc[1], acc[2])
        pitch = math.atan2(-acc[0], math.hypot(acc[1], acc[2]))
        q = quat_from_euler(roll, pitch, 0.0)
        P0 = np.zeros((N_CORE + len(self._bias_index),) * 2)
        f_norm = float(np.linalg.norm(acc))
        ba = np.zeros(3)
        if self._static(cfg.init_static_s) and len(recent) >= 3:
            p_ant, v, bg = np.mean(recent, axis=0), np.zeros(3), np.asarray(gyro)
            # at rest |f| = g: what is left over lies along the vertical, as an accel bias
            ba = (f_norm - GRAVITY_MPS2) * np.asarray(acc) / f_norm
            sig_v, sig_bg, self.status = 0.05, 0.005, "running (started at rest)"
        elif waited_s >= cfg.init_max_wait_s and len(self._fixes) >= 2:
            (t0, p0), (t1, p1) = self._fixes[-2], self._fixes[-1]
            p_ant, v, bg = p1, (p1 - p0) / max((t1 - t0) / 1e9, 1e-3), np.zeros(3)
            sig_v, sig_bg, self.status = 1.0, 0.02, "running (started while moving)"
        else:
            return
        self.counters["initialisations"] += 1
        R0 = quat_to_matrix(q)
        p = p_ant - R0 @ self.lever
        sig_p = float(np.sqrt(max(np.trace(fix.covariance) / 3, 0.05**2)))
        np.fill_diagonal(P0, np.concatenate([
            np.full(3, sig_p**2), np.full(3, sig_v**2),
            [math.radians(2) ** 2, math.radians(2) ** 2, math.pi**2],
            np.full(3, sig_bg**2), np.full(3, cfg.acc_bias_sigma_mps2**2),
            np.full(len(self._bias_index), cfg.range_bias_sigma_m**2)]))
        # a range's offset is the tag's delay plus its anchor's: correlated a priori
        P0[N_CORE:, N_CORE:] += cfg.tag_delay_sigma_m**2
        self.ekf = Eskf(p, v, q, P0, cfg.imu_noise, len(self._bias_index), b_g=bg, b_a=ba)
        self.t_ns = t_ns

    def _align_heading(self, t_ns: int, fix: LsqFix | None, anchors: Array,
                       ranges: Array) -> None:
        """Until aligned the heading is held (an EKF linearised about a large yaw error
        turns falsely confident within a second of motion); then :class:`HeadingAligner`
        tells the yaw error and the EKF takes over with its σ."""
        ekf = self.ekf
        assert ekf is not None
        ekf.rotate_heading(0.0, HELD_YAW_SIGMA_RAD)
        if not self._aligner.wants_fix(t_ns):
            return
        fix = fix or self._lsq(anchors, ranges)
        result = None if fix is None else self._aligner.add_fix(t_ns, fix)
        if result is not None:
            ekf.rotate_heading(*result)
            self._aligned = True
            self.counters["heading_alignments"] += 1

    def _predict_to(self, t_ns: int) -> None:
        """Bring the state to the measurement time: hold the last IMU sample while it is fresh
        (one IMU period at most, normally); in an IMU gap, coast at constant velocity with
        growing uncertainty, so the ranges keep the position while the IMU is away."""
        ekf = self.ekf
        assert ekf is not None and self.t_ns is not None
        dt = (t_ns - self.t_ns) / 1e9
        if dt <= 0:
            return
        fresh = self._imu_t_ns is not None and \
            (t_ns - self._imu_t_ns) / 1e9 <= self.cfg.max_imu_gap_s
        if fresh and self._last_imu is not None:
            ekf.predict(self._last_imu[0], self._last_imu[1], dt)
        else:
            self._coasted = True
            ekf.p = [p + v * dt for p, v in zip(ekf.p, ekf.v, strict=True)]
            self._inflate(velocity_mps=1.0 * dt, attitude_rad=0.01 * dt,
                          position_m=0.5 * dt)
        self.t_ns = t_ns

    def _measurement_rows(self, ids: list[int], anchors: Array, ranges: Array,
                          fix: LsqFix | None) -> Rows:
        """Tight: one row per range (§4, range); loose: the fix's axes (§4, position)."""
        ekf = self.ekf
        assert ekf is not None
        R = ekf.R
        p_ant = np.array(ekf.p) + R @ self.lever
        H_th_lever = -R @ skew(self.lever)
        if self.cfg.mode is Mode.TIGHT:
            diff = p_ant - anchors
            dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
            keep = dist >= 1e-3  # the antenna on an anchor: no line of sight to linearise
            if not keep.all():
                ids = [a for a, k in zip(ids, keep, strict=True) if k]
                diff, dist, ranges = diff[keep], dist[keep], ranges[keep]
            U = diff / dist[:, None]
            H = np.zeros((len(ids), ekf.n))
            H[:, P_] = U
            H[:, TH_] = U @ H_th_lever
            h = dist
            for i, anchor_id in enumerate(ids):
                k = self._bias_index.get(anchor_id)
                if k is not None:
                    H[i, k] = 1.0
                    h[i] += ekf.b_r[k - N_CORE]
            var = np.full(len(ids), self.cfg.range_sigma_m**2)
            return Rows(H, ranges - h, var, [("range", str(a)) for a in ids])
        if fix is None:
            return Rows.empty(ekf.n)
        axes = 3 if self._fixed_z is None else 2
        H = np.zeros((axes, ekf.n))
        H[:, P_] = np.eye(3)[:axes]
        H[:, TH_] = H_th_lever[:axes]
        var = np.maximum(np.diag(fix.covariance)[:axes], 0.02**2)
        return Rows(H, fix.position_m[:axes] - p_ant[:axes], var,
                    [("position", "xyz"[axis]) for axis in range(axes)])

    def _constraints(self) -> list[Rows]:
        ekf = self.ekf
        assert ekf is not None
        n = ekf.n
        cfg = self.cfg
        rows = []
        # constant velocity looks like rest to an IMU: require a slow estimate as well
        slow = math.hypot(*ekf.v) < cfg.zupt_max_speed_mps
        if cfg.zupt and slow and self._static(cfg.static_window_s):
            self.counters["zupt"] += 1
            H = np.zeros((3, n))
            H[:, V_] = np.eye(3)
            rows.append(Rows(H, -np.array(ekf.v), np.full(3, cfg.zupt_sigma_mps**2),
                             [("zupt", axis) for axis in "xyz"]))
        if cfg.nhc:
            Rt = ekf.R.T
            v_b = Rt @ np.array(ekf.v)
            H = np.zeros((2, n))
            H[:, V_] = Rt[1:]
            H[:, TH_] = skew(v_b)[1:]
            rows.append(Rows(H, -v_b[1:], np.full(2, cfg.nhc_sigma_mps**2),
                             [("nhc", "y"), ("nhc", "z")]))
        if cfg.known_height_m is not None:
            H = np.zeros((1, n))
            H[0, 2] = 1.0
            rows.append(Rows(H, np.array([cfg.known_height_m - ekf.p[2]]),
                             np.array([cfg.height_sigma_m**2]), [("height", "z")]))
        return rows

    def _fuse(self, t_ns: int, rows: Rows) -> list[FusionReport]:
        ekf = self.ekf
        assert ekf is not None
        H, y, R, keys = rows
        if not keys:
            return []
        S = ekf.innovation_variances(H, R)
        nis = y * y / S
        accept = nis <= self._gate_1
        idx = np.array([k[0] == "position" for k in keys])
        if idx.any():  # a position fix is one 3-D measurement: gate it as one
            Hl = H[idx]
            Sl = Hl @ ekf.P @ Hl.T + np.diag(R[idx])
            nis_l = float(y[idx] @ np.linalg.solve(Sl, y[idx]))
            accept[idx] = nis_l <= self._gate_3
        ratio = nis / self._gate_1
        reports = [FusionReport(t_ns, kind, key, y_i, s_i, r_i, ok, "" if ok else
                                "innovation_gate")
                   for (kind, key), y_i, s_i, r_i, ok in zip(
                       keys, y.tolist(), S.tolist(), ratio.tolist(), accept.tolist(),
                       strict=True)]
        counters = self.counters
        for r in reports:
            counters[f"{r.kind}_{'accepted' if r.accepted else 'rejected'}"] += 1
        if accept.any():
            ekf.update(H[accept], y[accept], R[accept])
        return reports

    def _needs_recovery(self, reports: list[FusionReport]) -> bool:
        """Most ranges failing the gate for a while (NLOS, or a wrong state), or divergence."""
        ekf = self.ekf
        assert ekf is not None
        uwb = [r for r in reports if r.kind in ("range", "position") and not math.isnan(r.nis)]
        bad = sum(not r.accepted for r in uwb)
        self._bad_epochs = self._bad_epochs + 1 if uwb and bad > len(uwb) / 2 else 0
        diverged = not (math.isfinite(ekf.P.sum() + sum(ekf.p))  # NaN and inf propagate
                        and ekf.position_sigma_m().max() < 100.0)
        return diverged or self._bad_epochs >= self.cfg.reinit_after_bad_epochs

    def _recover(self, fix: LsqFix | None) -> None:
        """Restart position (and velocity) from UWB least squares, keeping the attitude."""
        ekf = self.ekf
        assert ekf is not None
        if fix is None:
            return
        self.counters["reinitialisations"] += 1
        self.status = "running (re-initialised from UWB after rejected ranges)"
        self._bad_epochs = 0
        ekf.p = (fix.position_m - ekf.R @ self.lever).tolist()
        ekf.v = [0.0, 0.0, 0.0]
        self._inflate(velocity_mps=1.0, attitude_rad=0.0, position_m=0.5)

    def _update_status(self) -> None:
        ekf = self.ekf
        assert ekf is not None
        unknown = not self._aligned or ekf.yaw_sigma_rad() >= math.radians(10)
        note = "; heading not yet observable"
        if unknown and note not in self.status:
            self.status = self.status.replace(")", note + ")")
        elif not unknown and note in self.status:
            self.status = self.status.replace(note, "")

    def _inflate(self, velocity_mps: float, attitude_rad: float, position_m: float = 0.0) -> None:
        ekf = self.ekf
        assert ekf is not None
        d = np.zeros(ekf.n)
        d[P_] = position_m**2
        d[V_] = velocity_mps**2
        d[TH_] = attitude_rad**2
        ekf.P[np.diag_indices(ekf.n)] += d



def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of χ² with 1 or 3 degrees of freedom, exactly.

    Written out rather than taken from ``scipy.stats``, whose import alone costs the daemon
    ~70 MB of its memory budget: χ²₁ is the square of a standard normal, and the χ²₃ CDF
    ``erf(√(x/2)) − √(2x/π)·e^(−x/2)`` is inverted by bisection.
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability must be within (0, 1), got {p}")
    if dof == 1:
        return NormalDist().inv_cdf((1.0 + p) / 2.0) ** 2
    if dof != 3:
        raise ValueError(f"only 1 or 3 degrees of freedom, got {dof}")

    def cdf3(x: float) -> float:
        return math.erf(math.sqrt(x / 2)) - math.sqrt(2 * x / math.pi) * math.exp(-x / 2)

    lo, hi = 0.0, 1.0
    while cdf3(hi) < p:
        hi *= 2
    for _ in range(100):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf3(mid) < p else (lo, mid)
    return (lo + hi) / 2
