"""The IMU's noise densities and the discrete process noise ``Q_d`` they give (docs/ekf.md §3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbd.fusion.core.layout import BA_, BG_, N_CORE, TH_, V_
from uwbd.fusion.core.rotation import Array

GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities.

    Accel white noise ``σ_a`` (m/s²/√Hz), gyro ``σ_g`` (rad/s/√Hz), bias random walks ``σ_ba``
    (m/s³/√Hz), ``σ_bg`` (rad/s²/√Hz), and the range-bias random walk ``σ_br`` (m/√s) when
    range-bias states are on. Defaults: a consumer MEMS IMU's datasheet densities
    (≈ 0.003 m/s²/√Hz, ≈ 0.0002 rad/s/√Hz for MPU-9250-class parts) raised 3-5× for
    vibration and temperature, which real mountings add.
    """

    acc: float = 0.01
    gyro: float = 0.001
    acc_bias: float = 1e-3
    gyro_bias: float = 1e-4
    range_bias: float = 1e-4


def process_noise(noise: ImuNoise, n_range_bias: int, aux_tau_s: Array | None,
                  aux_sigma: Array | None) -> tuple[Array, Array, Array]:
    """What §3 takes for ``Q_d``: its diagonal per second (n), and per range-model state the
    Gauss–Markov time constant ``τ`` (inf: a random walk, whose rate the diagonal holds)
    and stationary variance. ``aux_sigma``: each state's stationary σ (Gauss–Markov) or σ
    per √s (a random walk; 0: a constant); None: random walks at ``noise.range_bias``."""
    q_rate = np.zeros(N_CORE + n_range_bias)
    q_rate[V_] = noise.acc**2
    q_rate[TH_] = noise.gyro**2
    q_rate[BG_] = noise.gyro_bias**2
    q_rate[BA_] = noise.acc_bias**2
    tau = (np.full(n_range_bias, np.inf) if aux_tau_s is None
           else np.asarray(aux_tau_s, dtype=float).reshape(n_range_bias))
    markov = np.isfinite(tau)
    sigma = (np.full(n_range_bias, noise.range_bias) if aux_sigma is None
             else np.asarray(aux_sigma, dtype=float).reshape(n_range_bias))
    # a random walk's rate (0: a constant); a Gauss–Markov state's Q is its decay's
    q_rate[N_CORE:] = np.where(markov, 0.0, sigma**2)
    return q_rate, tau, np.where(markov, sigma**2, 0.0)
