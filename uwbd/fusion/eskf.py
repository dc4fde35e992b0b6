"""Error-state EKF: strapdown INS nominal state plus a linear error state (docs/ekf.md).

Symbols follow the derivation: ``p v q b_g b_a b_r`` nominal, ``δx`` error, ``F Φ Q_d P H R
S K y``. The per-IMU-sample path (:meth:`Eskf.predict`) is plain float arithmetic; the
covariance is propagated once per update interval (:meth:`Eskf.propagate`).

This file is the reference: :meth:`Eskf.predict`, :meth:`Eskf.propagate` and
:meth:`Eskf.sequential_update` run a line-by-line C translation (``_core.c``) when it is
built (:mod:`.native`), and the code here otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from uwbd.fusion import native
from uwbd.fusion.robust import RowPolicy
from uwbd.fusion.rotation import Array, quat_to_matrix, skew

GRAVITY_MPS2 = 9.80665
Vector = Sequence[float] | Array
# error-state layout
P_, V_, TH_, BG_, BA_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
N_CORE = 15


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


class Row(NamedTuple):
    """One scalar of a sequential update: innovation, its variance, the weight it was fused
    with (0: not fused), and whether it was skipped as numerically impossible."""

    innovation: float
    variance: float
    weight: float
    numerical: bool


RawRow = tuple[float, float, float, bool]  # a Row's fields as the C core returns them


class Eskf:
    """The filter's state and the algebra on it; policy (gating, modes) lives in ``Filter``."""

    def __init__(self, p: Vector, v: Vector, q: Vector,
                 P0: Array, noise: ImuNoise, n_range_bias: int = 0,
                 b_g: Vector = (0.0, 0.0, 0.0),
                 b_a: Vector = (0.0, 0.0, 0.0), aux_tau_s: Array | None = None,
                 aux_sigma: Array | None = None, gravity_mps2: float = GRAVITY_MPS2) -> None:
        """``n_range_bias`` range-model states follow ``P0``: by default random walks
        (``noise.range_bias``); where ``aux_tau_s`` is finite, first-order Gauss–Markov
        processes with time constant ``τ`` and stationary σ ``aux_sigma`` (§3).
        ``gravity_mps2``: the local gravity the INS subtracts."""
        self.gravity_mps2 = float(gravity_mps2)
        self.n = N_CORE + n_range_bias
        if P0.shape != (self.n, self.n):
            raise ValueError(f"P0 must be {self.n}x{self.n}, got {P0.shape}")
        self.p, self.v, self.q = list(map(float, p)), list(map(float, v)), list(map(float, q))
        self.b_g, self.b_a = list(map(float, b_g)), list(map(float, b_a))
        self.b_r = np.zeros(n_range_bias)
        self.P = P0.astype(float).copy()
        self.noise = noise
        self._reset_interval()
        self.last_dx = np.zeros(self.n)
        # since the last take_epoch(): the core's Φ (smoothing) and the INS's own Δv (heading
        # alignment), over however many propagate() calls
        self._Phi_epoch = np.eye(N_CORE)
        self.keep_transition = True  # Φ kept for take_epoch(with_phi); off, not multiplied
        self._dv_epoch = [0.0, 0.0, 0.0]
        self._epoch_propagated = False  # Φ and the decays differ from I and 1
        # constants of propagate() and update()
        self._I = np.eye(self.n)
        self._I_core = np.eye(N_CORE)
        self._diag = np.diag_indices(self.n)
        self._F_template = np.zeros((N_CORE, N_CORE))
        self._F_template[P_, V_] = np.eye(3)
        self._F_template[TH_, BG_] = -np.eye(3)
        self._q_rate = np.zeros(self.n)  # diagonal of Q per second
        self._q_rate[V_] = noise.acc**2
        self._q_rate[TH_] = noise.gyro**2
        self._q_rate[BG_] = noise.gyro_bias**2
        self._q_rate[BA_] = noise.acc_bias**2
        self._q_rate[N_CORE:] = noise.range_bias**2
        self._tau = np.full(n_range_bias, np.inf) if aux_tau_s is None else np.asarray(aux_tau_s)
        self._markov = np.flatnonzero(np.isfinite(self._tau))
        self._markov_columns = tuple(N_CORE + int(i) for i in self._markov)  # (for C)
        self._q_rate[N_CORE + self._markov] = 0.0
        self._markov_var = (np.zeros(0) if aux_sigma is None
                            else np.asarray(aux_sigma)[self._markov] ** 2)
        self._no_decay = np.ones(n_range_bias)
        self._decay_epoch = self._no_decay.copy()
        self._core = native.core  # None: the pure-Python code below
        self._clamp_key: tuple[Array, float] | None = None
        self._clamp_limit = np.zeros(0)

    # -- nominal propagation: every IMU sample -------------------------------------------
    def predict(self, acc_b: Vector, gyro_b: Vector, dt: float) -> None:
        """Integrate one IMU sample over ``dt`` seconds (docs/ekf.md §2)."""
        if self._core is not None:
            self.q = self._core.predict(self.p, self.v, self.q, self.b_g, self.b_a,
                                        self._sum_fn, self._sum_w, acc_b, gyro_b, dt,
                                        self.gravity_mps2)
            self._T += dt
            return
        wx, wy, wz = (gyro_b[0] - self.b_g[0]) * dt, (gyro_b[1] - self.b_g[1]) * dt, \
            (gyro_b[2] - self.b_g[2]) * dt
        fx, fy, fz = acc_b[0] - self.b_a[0], acc_b[1] - self.b_a[1], acc_b[2] - self.b_a[2]
        qw, qx, qy, qz = self.q
        # a = R f + g, with R from q (before the attitude step: f was measured over dt)
        ax = (1 - 2 * (qy * qy + qz * qz)) * fx + 2 * (qx * qy - qw * qz) * fy \
            + 2 * (qx * qz + qw * qy) * fz
        ay = 2 * (qx * qy + qw * qz) * fx + (1 - 2 * (qx * qx + qz * qz)) * fy \
            + 2 * (qy * qz - qw * qx) * fz
        az = 2 * (qx * qz - qw * qy) * fx + 2 * (qy * qz + qw * qx) * fy \
            + (1 - 2 * (qx * qx + qy * qy)) * fz
        self._sum_fn[0] += ax * dt
        self._sum_fn[1] += ay * dt
        self._sum_fn[2] += az * dt
        self._sum_w[0] += wx
        self._sum_w[1] += wy
        self._sum_w[2] += wz
        self._T += dt
        az -= self.gravity_mps2
        p, v = self.p, self.v
        p[0] += (v[0] + 0.5 * ax * dt) * dt
        p[1] += (v[1] + 0.5 * ay * dt) * dt
        p[2] += (v[2] + 0.5 * az * dt) * dt
        v[0] += ax * dt
        v[1] += ay * dt
        v[2] += az * dt
        self.q = _turned(self.q, wx, wy, wz)

    # -- covariance propagation: once per update interval --------------------------------
    def _reset_interval(self) -> None:
        self._T = 0.0
        self._sum_fn = [0.0, 0.0, 0.0]
        self._sum_w = [0.0, 0.0, 0.0]

    @property
    def interval_s(self) -> float:
        """Time integrated since the last :meth:`propagate`."""
        return self._T

    def take_epoch(self, with_phi: bool = True
                   ) -> tuple[Array | None, tuple[float, float, float]]:
        """Since the last call: the state transition ``Φ`` (the product over every
        :meth:`propagate`; only ``with_phi``, for smoothing) and ``Σ R f Δt``, the INS's
        own velocity change (gravity aside) in the navigation frame, untouched by any
        measurement, over the propagated intervals."""
        Phi = None
        if with_phi:
            if not self.keep_transition:
                raise RuntimeError("take_epoch(with_phi=True) with keep_transition off")
            Phi = np.eye(self.n)
            Phi[:N_CORE, :N_CORE] = self._Phi_epoch
            Phi[N_CORE:, N_CORE:] = np.diag(self._decay_epoch)
        dv = self._dv_epoch
        self._dv_epoch = [0.0, 0.0, 0.0]
        if self._epoch_propagated:  # else both are still identity and ones
            self._epoch_propagated = False
            if self.keep_transition:  # (else never multiplied: still identity and ones)
                self._Phi_epoch = self._I_core.copy()  # (np.eye: 1 µs more)
                self._decay_epoch = self._no_decay.copy()
        return Phi, (dv[0], dv[1], dv[2])

    def rotate_heading(self, dpsi: float, yaw_sigma_rad: float) -> None:
        """Turn the nominal attitude by ``dpsi`` about the navigation z axis (a coarse heading
        alignment) and restart the heading's variance at ``yaw_sigma_rad``, uncorrelated with
        the rest; roll and pitch statistics are kept. The velocity is left alone: position
        fixes kept it right while the heading was wrong."""
        # quat_mul((cos, 0, 0, sin), q) term by term in floats: numpy's float64 arithmetic,
        # the same bits at a tenth of the cost (it runs at every update while aligning)
        c, s = math.cos(dpsi / 2), math.sin(dpsi / 2)
        w, x, y, z = self.q
        q = np.array((c * w - 0.0 * x - 0.0 * y - s * z, c * x + 0.0 * w + 0.0 * z - s * y,
                      c * y - 0.0 * z + 0.0 * w + s * x, c * z + 0.0 * y - 0.0 * x + s * w))
        self.q = (q / np.linalg.norm(q)).tolist()
        k = TH_.start + 2  # nav-frame yaw error
        if self._core is not None:  # the same, on the attitude rows and columns only
            w, x, y, z = self.q  # R (quat_to_matrix) row by row, and its transpose
            G = (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
            P = self.P = np.ascontiguousarray(self.P)
            self._core.turn_attitude_covariance(P, G)
            P[k, :] = 0.0
            P[:, k] = 0.0
            P[k, k] = yaw_sigma_rad**2
            self._core.turn_attitude_covariance(P, G[0::3] + G[1::3] + G[2::3])
            return
        R = self.R
        T = self._I.copy()  # body-frame attitude error -> nav-frame attitude error
        T[TH_, TH_] = R
        P = T @ self.P @ T.T
        P[k, :] = 0.0
        P[:, k] = 0.0
        P[k, k] = yaw_sigma_rad**2
        self.P = T.T @ P @ T

    def propagate(self) -> None:
        """``P ← Φ P Φᵀ + Q_d`` over the interval accumulated by :meth:`predict` (§3).

        Only the 15 core states have coupled dynamics (range-model states are random walks,
        Φ = I, or Gauss–Markov, Φ = e^(−T/τ) on the diagonal), so Φ is built and applied on
        the core rows and columns, and the decays on their own."""
        T = self._T
        if T <= 0.0:
            return
        for i in range(3):
            self._dv_epoch[i] += self._sum_fn[i]
        self._epoch_propagated = True
        symmetrised = False
        if self._core is not None:
            P = self.P = np.ascontiguousarray(self.P)
            # with no Gauss–Markov step between, symmetrised in the same call (same numbers)
            symmetrised = not len(self._markov)
            self._core.propagate_core(P, self._Phi_epoch if self.keep_transition else None,
                                      self.q, self._sum_fn, self._sum_w, T, self._q_rate,
                                      symmetrised)
        else:
            R = self.R
            f_n = np.array(self._sum_fn) / T
            w = np.array(self._sum_w) / T
            F = self._F_template.copy()
            F[V_, TH_] = -skew(f_n) @ R  # −R [f]× = −[R f]× R
            F[V_, BA_] = -R
            F[TH_, TH_] = -skew(w)
            A = F * T
            Phi = self._I_core + A + 0.5 * (A @ A)
            if self.keep_transition:
                self._Phi_epoch = Phi @ self._Phi_epoch
            P = self.P
            P[:N_CORE, :] = Phi @ P[:N_CORE, :]
            P[:, :N_CORE] = P[:, :N_CORE] @ Phi.T
            P[self._diag] += self._q_rate * T
        if not symmetrised and not self._markov_step(P, T, symmetrise=True):
            self.P = 0.5 * (P + P.T)
        self._reset_interval()

    def _markov_step(self, P: Array, T: float, symmetrise: bool = False) -> bool:
        """Gauss–Markov states decay towards 0 over ``T``; Q keeps their σ stationary. On
        the C core (in place), with ``symmetrise`` P is made symmetric in the same call, as
        ``0.5 * (P + P.T)`` makes it: True then."""
        m = self._markov
        if not len(m):
            return False
        self._epoch_propagated = True  # the decays are no longer ones
        phi = np.exp(-T / self._tau[m])
        core = self._core
        b_r = self.b_r
        decay = self._decay_epoch if self.keep_transition else None  # (Φ's diagonal part)
        if core is not None and P.flags.c_contiguous and b_r.flags.c_contiguous \
                and (decay is None or decay.flags.c_contiguous):
            core.markov_step(P, self._markov_columns, phi, self._markov_var, b_r, decay,
                             symmetrise)
            return symmetrise
        k = N_CORE + m
        P[k, :] *= phi[:, None]
        P[:, k] *= phi[None, :]
        P[k, k] += self._markov_var * (1.0 - phi * phi)
        b_r[m] *= phi
        if decay is not None:
            decay[m] *= phi
        return False

    def coast(self, dt: float, accel_sigma_mps2: float, yaw_rate_sigma_rps: float,
              tilt_rate_sigma_rps: float) -> None:
        """No IMU: constant velocity for ``dt`` (§3, coasting). ``Φ`` couples position to
        velocity, so the ranges still correct the velocity; white acceleration of σ
        ``accel_sigma_mps2`` and turns about the vertical of σ ``yaw_rate_sigma_rps`` (per
        √s) widen ``P``; roll and pitch, which gravity bounds, by ``tilt_rate_sigma_rps``."""
        p, v = self.p, self.v
        for i in range(3):
            p[i] += v[i] * dt
        P = self.P
        P[P_, :] += dt * P[V_, :]
        P[:, P_] += dt * P[:, V_]
        qa = accel_sigma_mps2**2
        for i in range(3):
            P[i, i] += qa * dt**3 / 3
            P[i, 3 + i] += qa * dt**2 / 2
            P[3 + i, i] += qa * dt**2 / 2
            P[3 + i, 3 + i] += qa * dt
        aux = self._diag[0][N_CORE:]
        P[aux, aux] += self._q_rate[N_CORE:] * dt  # the range-model random walks
        self._markov_step(P, dt)
        up_b = self.R[2]  # the navigation z axis in body axes (Rᵀ e_z)
        P[TH_, TH_] += (yaw_rate_sigma_rps**2 - tilt_rate_sigma_rps**2) * dt * np.outer(
            up_b, up_b) + tilt_rate_sigma_rps**2 * dt * np.eye(3)
        self.P = 0.5 * (P + P.T)

    def tilt_from_gravity_rad(self, f_body: Array) -> float:
        """Angle between the vertical and a specific force measured at rest, turned into the
        navigation frame by the attitude: 0 when the tilt is right."""
        f_n = self.R @ f_body
        norm = float(np.linalg.norm(f_n))
        return math.acos(min(max(f_n[2] / norm, -1.0), 1.0)) if norm > 0 else 0.0

    def yaw_rad(self) -> float:
        w, x, y, z = self.q
        return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))

    def tilt_sigma_rad(self) -> float:
        """σ of the roll/pitch error: the attitude error about the horizontal nav axes."""
        Rn = self.R
        cov = Rn @ self.P[TH_, TH_] @ Rn.T
        return math.sqrt(max((cov[0, 0] + cov[1, 1]) / 2, 0.0))

    # -- measurement update --------------------------------------------------------------
    def sequential_update(self, H: Array, y: Array, R: Array,
                          decide: Callable[[int, float, float], float] | RowPolicy,
                          considered: slice | None = None) -> list[Row]:
        """Fuse rows ``H`` (m×n), residuals ``y`` at the prior, noise variances ``R``, one
        scalar at a time (docs/ekf.md §5), then inject and reset.

        For row ``i``, at the state the rows before it left: innovation ``ν = y_i − H_i δx``
        with variance ``S = H_i P H_iᵀ + R_i``; ``decide(i, ν, S)`` returns the weight ``w``
        (0 skips the row, 1 is the plain Kalman update, ``0 < w < 1`` de-weights it: the gain
        is computed with ``R_i / w``; a :class:`~uwbd.fusion.robust.RowPolicy` is such a
        function that the C core reads without calling back). The covariance always follows
        the Joseph form with the nominal ``R_i``, which is right for any gain::

            P ← (I − k h) P (I − k h)ᵀ + R_i k kᵀ = P − k uᵀ − u kᵀ + S k kᵀ,  u = P hᵀ

        ``considered`` states are not corrected (their gain is zeroed, Schmidt's
        consider filter); the Joseph form keeps their covariance right.

        A row whose ``S`` is not finite or falls below ``R_i`` (``P`` lost its positive
        semi-definiteness along ``h``) is skipped and marked ``numerical``.
        """
        if self._core is not None:  # the rows, the injection and the reset in one call
            dx = np.zeros(self.n)
            c0, c1 = self._considered_columns(considered)
            P = self.P = np.ascontiguousarray(self.P, dtype=float)
            return self._corrected(dx, self._core.update_and_inject(
                P, np.ascontiguousarray(H, dtype=float), np.ascontiguousarray(y, dtype=float),
                np.ascontiguousarray(R, dtype=float), decide, c0, c1, dx, self.p, self.v,
                self.q, self.b_g, self.b_a, self.b_r))
        P, dx, rows, fused = self._sequential_rows(H, y, R, decide, considered)
        if fused:
            self.P = 0.5 * (P + P.T)
            self.inject(dx)
        return rows

    def fuse_ranges(self, lever_m: Array, anchors: Array, ranges: Array, var: Array,
                    columns: tuple[tuple[int, ...], ...], extra: tuple[Array, Array, Array],
                    decide: RowPolicy, considered: slice | None) -> list[RawRow] | None:
        """A tight epoch on the C core in one call: the rows of
        :func:`uwbd.fusion.measurements.range_rows` (``columns``: each range's range-model
        state columns), then ``extra`` rows ``(H, y, R)``, through :meth:`sequential_update`.
        ``None``, with nothing changed, where the core is not built or a range needs the
        reference (an antenna within 1 mm of its anchor): the caller runs those two then."""
        if self._core is None:
            return None
        dx = np.zeros(self.n)
        c0, c1 = self._considered_columns(considered)
        P = self.P = np.ascontiguousarray(self.P, dtype=float)
        H, y, R = extra
        out = self._core.fuse_ranges(
            P, dx, self.p, self.v, self.q, self.b_g, self.b_a, self.b_r, lever_m,
            np.ascontiguousarray(anchors, dtype=float), np.ascontiguousarray(ranges, dtype=float),
            np.ascontiguousarray(var, dtype=float), columns,
            np.ascontiguousarray(H, dtype=float), np.ascontiguousarray(y, dtype=float),
            np.ascontiguousarray(R, dtype=float), decide, c0, c1)
        return None if out is None else self._taken(dx, out)  # Row's fields, as tuples

    def _considered_columns(self, considered: slice | None) -> tuple[int, int]:
        c0, c1, step = (0, 0, 1) if considered is None else considered.indices(self.n)
        if step != 1:
            raise ValueError("considered states: a slice of step 1")
        return c0, c1

    def _corrected(self, dx: Array, out: tuple[list[tuple[float, float, float, bool]],
                                              list[float] | None]) -> list[Row]:
        """The C core's (rows, new q): when a row was fused, P and the state are corrected
        already; the new attitude and ``δx`` are kept here."""
        return [Row(*r) for r in self._taken(dx, out)]

    def _taken(self, dx: Array, out: tuple[list[RawRow], list[float] | None]) -> list[RawRow]:
        """:meth:`_corrected`, the rows left as the C core's tuples."""
        raw, q = out
        if q is not None:
            self.q = q
            self.last_dx = dx
        return raw

    def _sequential_rows(self, H: Array, y: Array, R: Array,
                         decide: Callable[[int, float, float], float] | RowPolicy,
                         considered: slice | None) -> tuple[Array, Array, list[Row], bool]:
        """The rows of :meth:`sequential_update` in Python: the posterior ``P`` and ``δx``
        (not yet injected), the rows, and whether any was fused."""
        P = self.P
        dx = np.zeros(self.n)
        rows = []
        fused = False
        for i in range(len(y)):
            h = H[i]
            u = P @ h
            r = float(R[i])
            s = float(h @ u) + r
            nu = float(y[i] - h @ dx)
            if not (math.isfinite(s) and math.isfinite(nu)) or s < r * (1 - 1e-9):
                rows.append(Row(nu, s, 0.0, True))
                continue
            w = decide(i, nu, s)
            rows.append(Row(nu, s, w, False))
            if not w > 0.0:  # 0, negative or NaN: not fused
                continue
            fused = True
            k = u / (s + r * (1.0 / w - 1.0))  # s − r + r/w
            if considered is not None:
                k[considered] = 0.0
            dx += k * nu
            M = np.outer(k, u - 0.5 * s * k)  # k uᵀ + u kᵀ − S k kᵀ = M + Mᵀ
            P = P - M - M.T
        return P, dx, rows, fused

    def update(self, H: Array, y: Array, R: Array) -> Array:
        """Every row fused with full weight: returns the injected ``δx``."""
        self.last_dx = np.zeros(self.n)
        self.sequential_update(H, y, R, _full_weight)
        return self.last_dx

    def inject(self, dx: Array) -> None:
        """Closed-loop correction of the nominal state, then the error reset ``P ← G P Gᵀ``."""
        self._inject_nominal(dx)
        # G = I except its attitude block I − ½[δθ]×: only those rows and columns change
        G_th = np.eye(3) - 0.5 * skew(dx[TH_])
        P = self.P
        P[TH_, :] = G_th @ P[TH_, :]
        P[:, TH_] = P[:, TH_] @ G_th.T

    def _inject_nominal(self, dx: Array) -> None:
        self.last_dx = dx
        d = dx.tolist()  # plain floats: numpy scalars would slow every later predict() ~3×
        p, v, b_g, b_a = self.p, self.v, self.b_g, self.b_a
        for i in range(3):
            p[i] += d[i]
            v[i] += d[3 + i]
            b_g[i] += d[9 + i]
            b_a[i] += d[12 + i]
        self.b_r += dx[N_CORE:]
        self.q = _turned(self.q, d[6], d[7], d[8])

    # -- keeping P sane ----------------------------------------------------------------------
    def clamp_covariance(self, max_core_sigma: Array, max_aux_sigma: float) -> bool:
        """Variances within bounds and none negative; True if anything was clamped. Scaling
        a row and its column keeps ``P`` positive semi-definite."""
        key = self._clamp_key
        if key is None or key[0] is not max_core_sigma or key[1] != max_aux_sigma:
            self._clamp_key = (max_core_sigma, max_aux_sigma)  # the same every epoch: made once
            self._clamp_limit = np.concatenate(
                [max_core_sigma, np.full(self.n - N_CORE, max_aux_sigma)])**2
        limit = self._clamp_limit
        if self._core is not None:
            self.P = np.ascontiguousarray(self.P)
            if not self._core.diagonal_out_of_bounds(self.P, limit):
                return False
        d = np.diag(self.P)
        if self._core is None and not ((d > limit).any() or (d < 0).any()):
            return False
        scale = np.sqrt(np.minimum(1.0, limit / np.maximum(d, 1e-300)))
        self.P = self.P * scale[:, None] * scale[None, :]
        negative = np.diag(self.P) < 0
        if negative.any():
            self.P[self._diag] = np.where(negative, 1e-9, np.diag(self.P))
        return True

    def widen(self, states: slice, sigma_factor: float) -> None:
        """Multiply the σ of ``states`` (and their correlations' share) by ``sigma_factor``."""
        d = np.ones(self.n)
        d[states] = sigma_factor
        self.P = self.P * d[:, None] * d[None, :]

    # -- views ----------------------------------------------------------------------------
    @property
    def R(self) -> Array:
        """Body-to-navigation rotation matrix of the nominal attitude."""
        return quat_to_matrix(np.array(self.q))

    def yaw_sigma_rad(self) -> float:
        """Standard deviation of the heading error: the nav-z component of ``R δθ``."""
        w, x, y, z = self.q
        r = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])
        return math.sqrt(max(float(r @ self.P[TH_, TH_] @ r), 0.0))


def _full_weight(i: int, nu: float, s: float) -> float:
    return 1.0


def _turned(q: list[float], tx: float, ty: float, tz: float) -> list[float]:
    """``q ⊗ Exp(θ)`` normalised, in plain floats (the per-IMU-sample attitude step)."""
    angle = math.sqrt(tx * tx + ty * ty + tz * tz)
    if angle < 1e-9:
        dw, s = 1.0, 0.5
    else:
        dw, s = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    dx, dy, dz = s * tx, s * ty, s * tz
    qw, qx, qy, qz = q
    nw = qw * dw - qx * dx - qy * dy - qz * dz
    nx = qw * dx + qx * dw + qy * dz - qz * dy
    ny = qw * dy - qx * dz + qy * dw + qz * dx
    nz = qw * dz + qx * dy - qy * dx + qz * dw
    norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    return [nw / norm, nx / norm, ny / norm, nz / norm]
