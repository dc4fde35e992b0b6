"""The pseudo-measurements of :class:`~uwbd.fusion.filter.Filter`: ZUPT at rest, the
non-holonomic constraint, a known height, at a fixed rate whatever the ranges' (at 170 single
ranges a second they would otherwise weigh 17 times what they do with 10 Hz epochs); and,
twice a second, the attitude's tilt checked against gravity while the IMU and the UWB fixes
are both still. Its own state is when each last ran; it acts on the parts it is handed."""

from __future__ import annotations

import math

import numpy as np

from uwbd.fusion.models.measurements import Rows, height_rows, nhc_rows, zupt_rows
from uwbd.fusion.policy.estimate import Estimate, Findings
from uwbd.fusion.policy.fusing import EpochFusion
from uwbd.fusion.policy.propagation import ImuPropagation
from uwbd.fusion.policy.recovery import NS, Recovery
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness
from uwbd.fusion.settings import FilterConfig

CONSTRAINT_EVERY_NS = 95_000_000  # ZUPT, NHC, known height: about 10 Hz
TILT_CHECK_EVERY_NS = NS // 2


class Constraints:
    """The rows of the pseudo-measurements due (see module doc)."""

    def __init__(self, cfg: FilterConfig, est: Estimate, findings: Findings, window: ImuWindow,
                 stillness: UwbStillness, imu: ImuPropagation, recovery: Recovery,
                 fusion: EpochFusion) -> None:
        self.cfg, self.est, self.findings, self.window = cfg, est, findings, window
        self.stillness, self.imu, self.recovery, self.fusion = stillness, imu, recovery, fusion
        self._last_ns = -(2**63)  # when ZUPT, NHC and height rows were last added
        self._tilt_check_ns = -(2**63)

    def due(self, t_ns: int) -> list[Rows]:
        """The rows due at ``t_ns`` (none between their times)."""
        if t_ns - self._last_ns < CONSTRAINT_EVERY_NS:
            return []
        self._last_ns = t_ns
        return self._rows()

    def _rows(self) -> list[Rows]:
        ekf = self.est.ekf
        assert ekf is not None
        cfg = self.cfg
        rows = []
        # constant velocity looks like rest to an IMU: require a slow estimate, and a state
        # that the ranges have not moved either (a ZUPT would otherwise pin v at 0 for good)
        slow = math.hypot(*ekf.v) < cfg.zupt_max_speed_mps and self.stillness.still()
        t_ns = self.est.t_ns or 0
        tilt_check_due = t_ns - self._tilt_check_ns >= TILT_CHECK_EVERY_NS
        still_imu = ((slow and cfg.zupt) or tilt_check_due) and self.imu.fresh() \
            and self.imu.check.burst_s(t_ns) == 0.0 and self.window.static(cfg.static_window_s)
        if tilt_check_due:
            self._tilt_check_ns = t_ns
            # the IMU still and the UWB fixes too, whatever the velocity estimate says (a
            # wrong tilt makes it wrong): the mean specific force is gravity's reaction
            if still_imu and self.stillness.still(allow_noise=True):
                self.recovery.check_tilt_against_gravity()
            else:
                self.recovery.tilt_unchecked()
        self.fusion.at_rest = bool(cfg.zupt and slow and still_imu and self.est.relevel is None)
        if self.fusion.at_rest:
            self.est.counters["zupt"] += 1
            rows.append(zupt_rows(ekf, cfg.zupt_sigma_mps))
        if cfg.nhc:
            rows.append(nhc_rows(ekf, cfg.nhc_sigma_mps))
            if self.est.aligned and not self.fusion.at_rest:  # the direction of travel in body axes
                vx, vy, _ = (ekf.R.T @ np.asarray(ekf.v)).tolist()
                self.findings.mounting_yaw.add(vx, vy)
                self.est.monitor.mounting_inconsistent = \
                    self.findings.mounting_yaw.error_deg is not None
        if cfg.known_height_m is not None:
            rows.append(height_rows(ekf, cfg.known_height_m, cfg.height_sigma_m))
        return rows

