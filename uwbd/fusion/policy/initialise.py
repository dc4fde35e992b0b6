"""The filter's state at the start, and after a restart.

* **At rest** (the IMU still for ``init_static_s`` and at least 3 fixes over that time):
  gyro bias = mean rate, roll and pitch from the mean specific force, the vertical excess
  of ``|f|`` over ``g`` as an accelerometer bias, position = the rest's epochs solved
  together, an anchor that disagrees left out (:mod:`.fixes`; single ranges: the mean
  fix), velocity 0.
* **While moving** (no rest within ``init_max_wait_s``, or at once after a restart):
  roll and pitch from the mean specific force, position from the latest fix, velocity
  from a line fit through the last second of fixes, wider σ for velocity and gyro bias.
* **Carried over** (the attitude restarted in place after an IMU gap or a rejected burst, or
  levelled anew at rest): the position, velocity and biases of the estimate before, with
  its position σ; the tilt of the attitude before, or, when levelling, roll and pitch from
  gravity over the fresh samples with the yaw value kept.

The heading always starts unknown (σ 180°): :mod:`.alignment` finds it once the vehicle
moves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array, quat_from_euler, quat_to_matrix
from uwbd.fusion.core.state import new_eskf
from uwbd.fusion.policy.alignment import velocity_fit
from uwbd.fusion.policy.rest import ImuWindow

if TYPE_CHECKING:
    from uwbd.fusion.settings import FilterConfig

NS = 1_000_000_000


class Start(NamedTuple):
    """What a restart keeps of the estimate before it (navigation frame, IMU point): the
    biases whenever they are finite, the position and velocity only if asked to."""

    p_m: Array | None
    v_mps: Array | None
    b_g_rps: Array
    b_a_mps2: Array
    b_r_m: Array
    sigma_p_m: float
    q: Array | None = None  # the attitude to keep (None: level from gravity, keep yaw_rad)
    tilt_sigma_rad: float = math.radians(2)
    yaw_rad: float = 0.0  # the heading to keep when the tilt is levelled anew


def start_state(cfg: FilterConfig, window: ImuWindow, fix: LsqFix,
                recent: list[tuple[int, Array]], fixes: list[tuple[int, Array]],
                waited_long: bool, carry: Start | None, n_bias: int,
                lever_m: Array, n_multipath: int = 0, n_lever: int = 0,
                rest_m: Array | None = None, rest_spread_m: float = 0.0,
                bank: Sequence[int] = (), bank_var: Array | None = None, *, core: Core
                ) -> tuple[Eskf, str] | None:
    """The new filter state and how it started (``rest``, ``moving``, ``carried``), or
    ``None`` while the evidence is not enough yet. ``recent``: fixes of the last
    ``init_static_s``; ``fixes``: all kept ones (time-ordered); ``rest_m``: their epochs
    solved together (:meth:`~uwbd.fusion.policy.fixes.RangeWindow.rest_fix`), the position
    at rest where given, else the fixes' mean, and ``rest_spread_m`` how far the solutions
    its test could not rule out lie from it (the start's position σ is at least that);
    ``bank``: the anchors the bank's sub-filters each leave out."""
    means = window.means()
    if means is None:
        return None
    acc, gyro = means
    roll = math.atan2(acc[1], acc[2])
    pitch = math.atan2(-acc[0], math.hypot(acc[1], acc[2]))
    q = quat_from_euler(roll, pitch, 0.0)
    R0 = quat_to_matrix(q)
    f_norm = float(np.linalg.norm(acc))
    ba = np.zeros(3)
    sig_fix = float(np.sqrt(max(np.trace(fix.covariance) / 3, 0.05**2)))
    sig_tilt = math.radians(2)
    if carry is not None and carry.p_m is not None and carry.v_mps is not None:
        if carry.q is not None:
            q = np.asarray(carry.q)
            sig_tilt = max(carry.tilt_sigma_rad, math.radians(0.5))
        else:
            q = quat_from_euler(roll, pitch, carry.yaw_rad)
        R0 = quat_to_matrix(q)
        p, v, bg = carry.p_m, carry.v_mps, carry.b_g_rps
        sig_p, sig_v, sig_bg, how = max(carry.sigma_p_m, sig_fix), 1.0, 0.01, "carried"
    elif window.static(cfg.init_static_s) and len(recent) >= 3:
        p = (np.mean([x for _, x in recent], axis=0) if rest_m is None else rest_m) \
            - R0 @ lever_m
        v, bg = np.zeros(3), np.asarray(gyro)
        # at rest |f| = g: what is left over lies along the vertical, as an accel bias
        ba = (f_norm - cfg.gravity_mps2) * np.asarray(acc) / f_norm
        sig_p, sig_v, sig_bg, how = max(sig_fix, rest_spread_m), 0.05, 0.005, "rest"
    elif waited_long and len(fixes) >= 2:
        last = [(t, x) for t, x in fixes if t >= fixes[-1][0] - NS]
        if len(last) >= 5:
            v_xy, _ = velocity_fit(last)
            t_span = (last[-1][0] - last[0][0]) / NS
            v_z = (last[-1][1][2] - last[0][1][2]) / max(t_span, 1e-3)
            v = np.array([v_xy[0], v_xy[1], v_z])
            sig_v = 0.5
        else:
            (t0, p0), (t1, p1) = fixes[-2], fixes[-1]
            v, sig_v = (p1 - p0) / max((t1 - t0) / NS, 1e-3), 1.0
        p, bg = fix.position_m - R0 @ lever_m, np.zeros(3)
        sig_p, sig_bg, how = sig_fix, 0.02, "moving"
    else:
        return None
    sig_ba = cfg.acc_bias_sigma_mps2
    if carry is not None:  # the biases of the estimate before: better than none
        bg, ba, sig_bg, sig_ba = carry.b_g_rps, carry.b_a_mps2, min(sig_bg, 0.01), sig_ba / 2
    n_aux = n_bias + n_multipath + n_lever
    P0 = np.zeros((N_CORE + n_aux,) * 2)
    np.fill_diagonal(P0, np.concatenate([
        np.full(3, sig_p**2), np.full(3, sig_v**2),
        [sig_tilt**2, sig_tilt**2, math.pi**2],
        np.full(3, sig_bg**2), np.full(3, sig_ba**2),
        np.full(n_bias, cfg.range_bias_sigma_m**2),
        np.full(n_multipath, cfg.multipath_sigma_m**2),
        np.full(n_lever, cfg.lever_arm_sigma_m**2)]))
    # a range's offset is the tag's delay plus its anchor's: correlated a priori
    delays = slice(N_CORE, N_CORE + n_bias)
    P0[delays, delays] += cfg.tag_delay_sigma_m**2
    tau = np.concatenate([np.full(n_bias, np.inf), np.full(n_multipath, cfg.multipath_tau_s),
                          np.full(n_lever, np.inf)])  # the lever arm's error: a constant
    # the offsets' random walk, multipath's stationary σ; the lever arm's error: no noise
    sigma = np.concatenate([np.full(n_bias, cfg.imu_noise.range_bias),
                            np.full(n_multipath, cfg.multipath_sigma_m), np.zeros(n_lever)])
    b_r = carry.b_r_m if carry is not None and len(carry.b_r_m) == n_aux else None
    ekf = new_eskf(core, p, v, q, P0, cfg.imu_noise, n_aux, b_g=bg, b_a=ba, aux_tau_s=tau,
                   aux_sigma=sigma, gravity_mps2=cfg.gravity_mps2, b_r=b_r, bank=bank,
                   bank_var=bank_var)
    return ekf, how
