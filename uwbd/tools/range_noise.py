"""The noise a range model leaves (``uwbd calibrate-ranges``, steps 4 and 5 of
:mod:`uwbd.tools.range_calibration`): a robust σ of the core, the residuals'
autocovariance split into white noise and a fast and a slow correlated part, and the NLOS
tail: a Gaussian core with an exponential tail each side, fitted by maximum likelihood, and
where the long one overtakes the core."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq, least_squares, minimize

from uwbd.fusion.core.rotation import Array

TAIL_SIGMA = 3.0
# a long tail thinner than this, or overtaking the core only beyond MAX_ONSET_SIGMA, says
# too little of NLOS to set the update's scale (a Gaussian's own fit finds a trace of one)
MIN_TAIL_FRACTION = 0.01
MAX_ONSET_SIGMA = 4.0
SQRT_2PI = math.sqrt(2 * math.pi)
MAX_LAG_S = 20.0
LAG_BIN_S = 0.1


def robust_sigma(e: Array) -> float:
    """1.4826 × the median absolute deviation from the median: σ of a Gaussian core."""
    return float(1.4826 * np.median(np.abs(e - np.median(e)))) if len(e) else math.nan


@dataclass(frozen=True)
class NlosTail:
    """The long side's exponential tail (step 5): its share of the ranges, its scale, and
    the length beyond which a range is likelier in it than in the core (None: a tail too
    thin to say, under ``MIN_TAIL_FRACTION`` or overtaking only beyond ``MAX_ONSET_SIGMA``
    σ)."""

    fraction: float
    scale_m: float
    onset_m: float | None


@dataclass
class NoiseShape:
    core_sigma_m: float
    long_fraction: float  # beyond TAIL_SIGMA σ, long
    short_fraction: float
    white_sigma_m: float
    fast_sigma_m: float
    fast_tau_s: float
    slow_sigma_m: float
    slow_tau_s: float
    nlos: NlosTail


def _autocovariance(t_ns: npt.NDArray[np.int64], anchor: npt.NDArray[np.int64], e: Array
                    ) -> tuple[Array, Array, float]:
    """The residuals' autocovariance by lag (bins of ``LAG_BIN_S`` up to ``MAX_LAG_S``),
    pooled over the anchors, and the variance at lag 0."""
    n_bins = int(MAX_LAG_S / LAG_BIN_S)
    total, count = np.zeros(n_bins), np.zeros(n_bins)
    var_sum, var_n = 0.0, 0
    for a in np.unique(anchor):
        mine = anchor == a
        t, x = t_ns[mine] / 1e9, e[mine] - np.mean(e[mine])
        var_sum, var_n = var_sum + float(x @ x), var_n + len(x)
        for k in range(1, len(x)):
            dt = t[k:] - t[:-k]
            if dt.min() > MAX_LAG_S:
                break
            b = (dt / LAG_BIN_S).astype(int)
            ok = b < n_bins
            np.add.at(total, b[ok], x[k:][ok] * x[:-k][ok])
            np.add.at(count, b[ok], 1)
    lags = np.asarray((np.arange(n_bins) + 0.5) * LAG_BIN_S, dtype=float)
    keep = count > 50
    return lags[keep], np.asarray(total[keep] / count[keep], dtype=float), var_sum / max(var_n, 1)


def _split_covariance(lags: Array, cov: Array, var0: float) -> tuple[float, float, float,
                                                                       float, float]:
    """``cov(τ) ≈ σ_f² e^(−τ/τ_f) + σ_s² e^(−τ/τ_s)``: (white σ, σ_f, τ_f, σ_s, τ_s)."""
    def model(x: Array) -> Array:
        vf, tf, vs, ts = x
        return np.asarray(vf * np.exp(-lags / tf) + vs * np.exp(-lags / ts), dtype=float)

    x0 = np.array([0.6 * var0, 1.0, 0.2 * var0, 30.0])
    lo, hi = [0.0, 0.1, 0.0, 10.0], [var0, 10.0, var0, 1000.0]
    sol = least_squares(lambda x: model(x) - cov, x0, bounds=(lo, hi))
    vf, tf, vs, ts = sol.x
    white = max(var0 - vf - vs, 0.0)
    return math.sqrt(white), math.sqrt(vf), float(tf), math.sqrt(vs), float(ts)


def noise_shape(t_ns: npt.NDArray[np.int64], anchor: npt.NDArray[np.int64], e: Array
                ) -> NoiseShape:
    """The noise of the residuals ``e`` (ranges at ``t_ns`` to ``anchor``) left by the
    model (see :mod:`uwbd.tools.range_calibration`, steps 4 and 5)."""
    sigma = robust_sigma(e)
    centred = e - np.median(e)
    z = centred / sigma
    core = np.abs(z) <= TAIL_SIGMA
    lags, cov, var0 = _autocovariance(t_ns[core], anchor[core], centred[core])
    white, fast, tau_f, slow, tau_s = _split_covariance(lags, cov, var0)
    return NoiseShape(sigma, float(np.mean(z > TAIL_SIGMA)), float(np.mean(z < -TAIL_SIGMA)),
                      white, fast, tau_f, slow, tau_s, nlos_tail(z, sigma))


def nlos_tail(z: Array, sigma_m: float) -> NlosTail:
    """Step 5 on standardised residuals ``z`` (σ ``sigma_m``): the maximum-likelihood
    mixture ``(1 − ε₊ − ε₋) φ(z) + ε₊ e^(−z/λ₊)/λ₊ [z > 0] + ε₋ e^(z/λ₋)/λ₋ [z < 0]``, and
    where its long tail overtakes its core."""
    z = np.asarray(z, dtype=float)
    z = z[np.isfinite(z)]
    positive = z > 0

    def parts(x: Array) -> tuple[float, float, float, float, float]:
        a, b, log_lp, log_lm = x
        ep, em = 0.5 / (1 + math.exp(-a)), 0.5 / (1 + math.exp(-b))  # each below one half
        return 1 - ep - em, ep, em, math.exp(log_lp), math.exp(log_lm)

    def nll(x: Array) -> float:
        core, ep, em, lp, lm = parts(x)
        tail = np.where(positive, ep / lp * np.exp(-np.abs(z) / lp),
                        em / lm * np.exp(-np.abs(z) / lm))
        return float(-np.log(core * np.exp(-0.5 * z * z) / SQRT_2PI + tail).sum())

    x = minimize(nll, np.array([-2.0, -2.0, 0.5, 0.5]), method="Nelder-Mead",
                 options={"maxiter": 4000, "xatol": 1e-5, "fatol": 1e-5}).x
    core, ep, _, lp, _ = parts(x)

    def gap(t: float) -> float:  # log core − log long tail, at t σ
        return (math.log(core / SQRT_2PI) - 0.5 * t * t) - (math.log(ep / lp) - t / lp)

    grid = np.linspace(0.0, MAX_ONSET_SIGMA, 200)
    over = [k for k in range(1, len(grid)) if gap(grid[k - 1]) > 0 >= gap(grid[k])]
    onset = (float(brentq(gap, grid[over[0] - 1], grid[over[0]])) * sigma_m
             if over and ep >= MIN_TAIL_FRACTION else None)
    return NlosTail(ep, lp * sigma_m, onset)
