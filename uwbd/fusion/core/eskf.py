"""Error-state EKF: strapdown INS nominal state plus a linear error state (docs/ekf.md).

Symbols follow the derivation: ``p v q b_g b_a b_r`` nominal, ``δx`` error, ``F Φ Q_d P H R
S K y``. The per-IMU-sample path (:meth:`Eskf.predict`) is plain float arithmetic; the
covariance is propagated once per update interval (:meth:`Eskf.propagate`).

The reference, as docs/ekf.md reads: where the C core is built the filter runs
:class:`uwbd.fusion.core.state.CoreEskf`, the same operations on the C type's state
(``_core.State``); tests/test_core.py holds the two to each other."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from uwbd.fusion.core import bank as bank_ops
from uwbd.fusion.core.bank import bank_started, bank_update, bank_variances, clamped, symmetric
from uwbd.fusion.core.layout import BA_, BG_, N_CORE, P_, TH_, V_
from uwbd.fusion.core.noise import GRAVITY_MPS2, ImuNoise, process_noise
from uwbd.fusion.core.pose import PoseNumbers, pose_numbers
from uwbd.fusion.core.rotation import Array, quat_to_matrix, skew, turned
from uwbd.fusion.core.weights import RawRow, Row, RowPolicy, full_weight

Vector = Sequence[float] | Array


class Eskf:
    """The filter's state and the algebra on it; policy (gating, modes) lives in ``Filter``."""

    fuses_ranges = False  # fuse_ranges takes a tight epoch in one call (CoreEskf)
    bank_resets = 0  # how often the bank started anew (a restore, a move, an adoption)
    core_state: object = None  # CoreEskf's C State, which the C IMU front integrates into
    # lists of floats here, numpy views of the C core's memory in CoreEskf
    p: list[float] | Array
    v: list[float] | Array
    q: list[float] | Array
    b_g: list[float] | Array
    b_a: list[float] | Array

    def __init__(self, p: Vector, v: Vector, q: Vector, P0: Array, noise: ImuNoise,
                 n_range_bias: int = 0, b_g: Vector = (0.0, 0.0, 0.0),
                 b_a: Vector = (0.0, 0.0, 0.0), aux_tau_s: Array | None = None,
                 aux_sigma: Array | None = None, gravity_mps2: float = GRAVITY_MPS2,
                 b_r: Vector | None = None, bank: Sequence[int] = (),
                 bank_var: Array | None = None) -> None:
        """``n_range_bias`` range-model states follow ``P0`` (their values ``b_r``, zeros
        by default): by default random walks (``noise.range_bias``); where ``aux_tau_s`` is
        finite, first-order Gauss–Markov processes with time constant ``τ``; ``aux_sigma``
        their σ (``noise.process_noise``, §3). ``gravity_mps2``: the INS's gravity.

        ``bank``: the anchor each sub-filter of the bank leaves out (§6): its offset from
        the nominal state ``bank_d[k]`` and covariance ``bank_P[k]`` advance with the main
        filter (its Φ, Q, rows and weights, its anchor's rows left out; a heading's turn
        turns them, dropping their heading offsets); a restore or a move starts it anew,
        each adding its ``bank_var`` (K×n) to ``P``'s diagonal (the lever member's)."""
        self.gravity_mps2 = float(gravity_mps2)
        self.n = N_CORE + n_range_bias
        if P0.shape != (self.n, self.n):
            raise ValueError(f"P0 must be {self.n}x{self.n}, got {P0.shape}")
        self.p, self.v, self.q = list(map(float, p)), list(map(float, v)), list(map(float, q))
        self.b_g, self.b_a = list(map(float, b_g)), list(map(float, b_a))
        self.b_r = np.zeros(n_range_bias) if b_r is None else np.array(b_r, dtype=float)
        if self.b_r.shape != (n_range_bias,):
            raise ValueError(f"b_r must hold {n_range_bias} numbers, got {self.b_r.shape}")
        self.P = P0.astype(float).copy()
        self.bank = tuple(int(a) for a in bank)
        self._bank_anchor = np.array(self.bank, dtype=np.int64)
        self.bank_var = bank_variances(bank_var, len(self.bank), self.n)
        self.bank_d, self.bank_P = bank_started(self.P, self.bank_var)
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
        self._I, self._I_core, self._diag = np.eye(self.n), np.eye(N_CORE), np.diag_indices(self.n)
        self._F_template = np.zeros((N_CORE, N_CORE))
        self._F_template[P_, V_] = np.eye(3)
        self._F_template[TH_, BG_] = -np.eye(3)
        self._q_rate, self._tau, var = process_noise(noise, n_range_bias, aux_tau_s, aux_sigma)
        self._markov = np.flatnonzero(np.isfinite(self._tau))
        self._markov_var = var[self._markov]  # (the Gauss–Markov states')
        self._no_decay = np.ones(n_range_bias)
        self._decay_epoch = self._no_decay.copy()
        self._clamp_key: tuple[Array, float] | None = None  # (made once: _clamp_limit_of)
        self._clamp_limit = np.zeros(0)

    # -- nominal propagation: every IMU sample -------------------------------------------
    def predict(self, acc_b: Vector, gyro_b: Vector, dt: float) -> None:
        """Integrate one IMU sample over ``dt`` seconds (docs/ekf.md §2)."""
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
        fn, w = self._sum_fn, self._sum_w
        fn[0], fn[1], fn[2] = fn[0] + ax * dt, fn[1] + ay * dt, fn[2] + az * dt
        w[0], w[1], w[2] = w[0] + wx, w[1] + wy, w[2] + wz
        self._T += dt
        az -= self.gravity_mps2
        p, v = self.p, self.v
        p[0], p[1], p[2] = (p[0] + (v[0] + 0.5 * ax * dt) * dt, p[1] + (v[1] + 0.5 * ay * dt) * dt,
                            p[2] + (v[2] + 0.5 * az * dt) * dt)
        v[0], v[1], v[2] = v[0] + ax * dt, v[1] + ay * dt, v[2] + az * dt
        self.q = turned(self.q, wx, wy, wz)

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
                self._Phi_epoch = self._I_core.copy()
                self._decay_epoch = self._no_decay.copy()
        return Phi, (dv[0], dv[1], dv[2])

    def rotate_heading(self, dpsi: float, yaw_sigma_rad: float) -> None:
        """Turn the nominal attitude by ``dpsi`` about the navigation z axis (a coarse heading
        alignment) and restart the heading's variance at ``yaw_sigma_rad``, uncorrelated with
        the rest; roll and pitch statistics are kept. The velocity is left alone: position
        fixes kept it right while the heading was wrong."""
        c, s = math.cos(dpsi / 2), math.sin(dpsi / 2)
        w, x, y, z = self.q  # (c, 0, 0, s) ⊗ q
        q = np.array((c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w))
        self.q = (q / np.linalg.norm(q)).tolist()
        T = self._I.copy()  # body-frame attitude error -> nav-frame attitude error
        R = T[TH_, TH_] = self.R
        k = TH_.start + 2  # nav-frame yaw error
        for main in (True, False):  # the main filter, the sub-filters
            P = T @ (self.P if main else self.bank_P) @ T.T
            P[..., k, :] = 0.0
            P[..., :, k] = 0.0
            P[..., k, k] = yaw_sigma_rad**2
            if main:
                self.P = T.T @ P @ T
            else:
                self.bank_P = T.T @ P @ T
        # the sub-filters' heading offsets dropped (the heading is the aligner's, for all)
        th = self.bank_d[:, TH_]
        th -= np.outer(th @ R[2], R[2])

    def _bank_reset(self) -> None:
        """The bank started anew from the main filter (:func:`.bank.bank_started`)."""
        self.bank_resets += 1
        self.bank_d, self.bank_P = bank_started(self.P, self.bank_var)

    def propagate(self) -> None:
        """``P ← Φ P Φᵀ + Q_d`` over the interval accumulated by :meth:`predict` (§3).

        Only the 15 core states have coupled dynamics (range-model states are random walks,
        Φ = I, or Gauss–Markov, Φ = e^(−T/τ) on the diagonal), so Φ is built and applied on
        the core rows and columns, and the decays on their own."""
        T = self._T
        if not T > 0.0:
            return
        for i in range(3):
            self._dv_epoch[i] += self._sum_fn[i]
        self._epoch_propagated = True
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
        for P in (self.P, self.bank_P):  # the main filter, the sub-filters: the same Φ and Q
            P[..., :N_CORE, :] = Phi @ P[..., :N_CORE, :]
            P[..., :, :N_CORE] = P[..., :, :N_CORE] @ Phi.T
            P[..., self._diag[0], self._diag[1]] += self._q_rate * T
        self.bank_d[:, :N_CORE] = self.bank_d[:, :N_CORE] @ Phi.T
        self._markov_step(T)
        self.P, self.bank_P = symmetric(self.P), symmetric(self.bank_P)
        self._reset_interval()

    def _markov_step(self, T: float) -> None:
        """Gauss–Markov states decay towards 0 over ``T``; Q keeps their σ stationary; on
        the main filter and every sub-filter."""
        m = self._markov
        if not len(m):
            return
        self._epoch_propagated = True  # the decays are no longer ones
        phi = np.exp(-T / self._tau[m])
        k = N_CORE + m
        for P in (self.P, self.bank_P):
            P[..., k, :] *= phi[:, None]
            P[..., :, k] *= phi[None, :]
            P[..., k, k] += self._markov_var * (1.0 - phi * phi)
        self.bank_d[:, k] *= phi
        self.b_r[m] *= phi
        if self.keep_transition:
            self._decay_epoch[m] *= phi

    def coast(self, dt: float, accel_sigma_mps2: float, yaw_rate_sigma_rps: float,
              tilt_rate_sigma_rps: float) -> None:
        """No IMU: constant velocity for ``dt`` (§3, coasting). ``Φ`` couples position to
        velocity, so the ranges still correct the velocity; white acceleration of σ
        ``accel_sigma_mps2`` and turns about the vertical of σ ``yaw_rate_sigma_rps`` (per
        √s) widen ``P``; roll and pitch, which gravity bounds, by ``tilt_rate_sigma_rps``."""
        p, v = self.p, self.v
        for c in range(3):
            p[c] += v[c] * dt
        self.bank_d[:, P_] += dt * self.bank_d[:, V_]
        qa, i, aux = accel_sigma_mps2**2, np.arange(3), self._diag[0][N_CORE:]
        for P in (self.P, self.bank_P):  # the main filter, the sub-filters
            P[..., P_, :] += dt * P[..., V_, :]
            P[..., :, P_] += dt * P[..., :, V_]
            P[..., i, i] += qa * dt**3 / 3
            P[..., i, 3 + i] += qa * dt**2 / 2
            P[..., 3 + i, i] += qa * dt**2 / 2
            P[..., 3 + i, 3 + i] += qa * dt
            P[..., aux, aux] += self._q_rate[N_CORE:] * dt  # the range-model random walks
        self._markov_step(dt)
        up_b = self.R[2]  # the navigation z axis in body axes (Rᵀ e_z)
        turn = (yaw_rate_sigma_rps**2 - tilt_rate_sigma_rps**2) * dt * np.outer(
            up_b, up_b) + tilt_rate_sigma_rps**2 * dt * np.eye(3)
        self.P[TH_, TH_] += turn
        self.bank_P[:, TH_, TH_] += turn
        self.P, self.bank_P = symmetric(self.P), symmetric(self.bank_P)

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
                          considered: slice | None = None,
                          ids: Sequence[int] | None = None) -> list[Row]:
        """Fuse rows ``H`` (m×n), residuals ``y`` at the prior, noise variances ``R``, one
        scalar at a time (docs/ekf.md §5), then inject and reset. ``ids``: the first rows'
        anchors (the bank's sub-filter of an anchor leaves its rows out; None: no row is an
        anchor's).

        For row ``i``, at the state the rows before it left: innovation ``ν = y_i − H_i δx``
        with variance ``S = H_i P H_iᵀ + R_i``; ``decide(i, ν, S)`` returns the weight ``w``
        (0 skips the row, 1 is the plain Kalman update, ``0 < w < 1`` de-weights it: the gain
        is computed with ``R_i / w``; a :class:`~uwbd.fusion.policy.robust.RowPolicy` is such a
        function that the C core reads without calling back). The covariance always follows
        the Joseph form with the nominal ``R_i``, which is right for any gain::

            P ← (I − k h) P (I − k h)ᵀ + R_i k kᵀ = P − k uᵀ − u kᵀ + S k kᵀ,  u = P hᵀ

        ``considered`` states are not corrected (their gain is zeroed, Schmidt's
        consider filter); the Joseph form keeps their covariance right.

        A row whose ``S`` is not finite or falls below ``R_i`` (``P`` lost its positive
        semi-definiteness along ``h``) is skipped and marked ``numerical``.

        The bank takes the same rows with the weights given here (:func:`.bank.bank_update`).
        """
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
            k = u / (s - r + r / w)
            if considered is not None:
                k[considered] = 0.0
            dx += k * nu
            P = P - np.outer(k, u) - np.outer(u, k) + s * np.outer(k, k)
        if fused:
            bank_update(self.bank_P, self.bank_d, self._bank_anchor, H, y, R,
                        [r.weight for r in rows], ids, considered, dx)
            self.P = 0.5 * (P + P.T)
            self.inject(dx)
        return rows

    def fuse_ranges(self, lever_m: Array, anchors: Array, ranges: Array, var: Array,
                    columns: tuple[tuple[int, ...], ...], lever_columns: tuple[int, ...],
                    extra: tuple[Array, Array, Array], decide: RowPolicy,
                    considered: slice | None, ids: Sequence[int] = ()
                    ) -> list[RawRow | None] | None:
        """A tight epoch in one call on the C core (:class:`CoreEskf`): the rows of
        ``measurements.range_rows`` (``columns``: each range's range-model states;
        ``lever_columns``: the lever arm's, or ``()``; ``ids``: their anchors), then
        ``extra`` rows ``(H, y, R)``, as :meth:`sequential_update` fuses them; ``None`` for
        a range with no line to linearise. The reference has no such call (``None``)."""
        return None

    def update(self, H: Array, y: Array, R: Array) -> Array:
        """Every row fused with full weight: returns the injected ``δx``."""
        self.last_dx = np.zeros(self.n)
        self.sequential_update(H, y, R, full_weight)
        return self.last_dx

    def inject(self, dx: Array) -> None:
        """Closed-loop correction of the nominal state, then the error reset ``P ← G P Gᵀ``."""
        self.last_dx = dx
        d = dx.tolist()  # plain floats: numpy scalars would slow every later predict() ~3×
        p, v, b_g, b_a = self.p, self.v, self.b_g, self.b_a
        for i in range(3):
            p[i] += d[i]
            v[i] += d[3 + i]
            b_g[i] += d[9 + i]
            b_a[i] += d[12 + i]
        self.b_r += dx[N_CORE:]
        self.q = turned(self.q, d[6], d[7], d[8])
        # G = I except its attitude block I − ½[δθ]×: only those rows and columns change
        G_th = np.eye(3) - 0.5 * skew(dx[TH_])
        P = self.P
        P[TH_, :] = G_th @ P[TH_, :]
        P[:, TH_] = P[:, TH_] @ G_th.T
        if len(self.bank):
            Pk = self.bank_P = symmetric(self.bank_P)
            Pk[:, TH_, :] = G_th @ Pk[:, TH_, :]
            Pk[:, :, TH_] = Pk[:, :, TH_] @ G_th.T

    # -- keeping P sane, repairs ----------------------------------------------------------
    def clamp_covariance(self, max_core_sigma: Array, max_aux_sigma: float) -> bool:
        """Variances within bounds and none negative; True if anything was clamped. Scaling
        a row and its column keeps ``P`` positive semi-definite."""
        limit = self._clamp_limit_of(max_core_sigma, max_aux_sigma)
        for k in range(len(self.bank)):  # (each sub-filter on its own)
            self.bank_P[k] = clamped(self.bank_P[k], limit)
        P = clamped(self.P, limit)
        if P is self.P:
            return False
        self.P = P
        return True

    def _clamp_limit_of(self, max_core_sigma: Array, max_aux_sigma: float) -> Array:
        """The variances' limits (the same every epoch: made once)."""
        key = self._clamp_key
        if key is None or key[0] is not max_core_sigma or key[1] != max_aux_sigma:
            self._clamp_key = (max_core_sigma, max_aux_sigma)
            self._clamp_limit = np.concatenate(
                [max_core_sigma, np.full(self.n - N_CORE, max_aux_sigma)])**2
        return self._clamp_limit

    def widen(self, states: slice, sigma_factor: float) -> None:
        """Multiply the σ of ``states`` (and their correlations' share) by ``sigma_factor``."""
        d = np.ones(self.n)
        d[states] = sigma_factor
        self.P = self.P * d[:, None] * d[None, :]
        self.bank_P = self.bank_P * d[None, :, None] * d[None, None, :]

    def add_variances(self, d: Array) -> None:
        """``P_ii += d_i``: what a step did not see (an unseen interval, a held heading)."""
        self.P[self._diag] += d
        self.bank_P[:, self._diag[0], self._diag[1]] += d

    def set_covariance(self, P: Array) -> None:
        """``P`` restored (the last finite one, widened); the bank anew."""
        self.P = np.array(P, dtype=float).reshape(self.n, self.n)
        self._bank_reset()

    def move_to(self, p: Vector, v: Vector) -> None:
        """Position and velocity set (a position reset to a UWB fix); the bank anew."""
        self.p, self.v = [float(c) for c in p], [float(c) for c in v]
        self._bank_reset()

    def adopt(self, k: int) -> None:
        """The main filter becomes the bank's sub-filter ``k`` (its anchor's fault found and
        excluded): the nominal state corrected by ``d_k`` as an update injects, ``P ←
        P_k``; then the bank anew."""
        if not 0 <= k < len(self.bank):
            raise IndexError(f"adopt: sub-filter {k} of {len(self.bank)}")
        self.P = self.bank_P[k].copy()
        self.inject(self.bank_d[k].copy())
        self._bank_reset()

    def restart_member(self, k: int) -> None:
        """The bank's sub-filter ``k`` alone started anew from the main filter."""
        d, Pk = bank_started(self.P, self.bank_var[k:k + 1])
        self.bank_d[k], self.bank_P[k] = d[0], Pk[0]

    def separation_numbers(self) -> bank_ops.SeparationNumbers:
        """The bank's numbers for the separation test (:func:`.bank.separation_numbers`)."""
        return bank_ops.separation_numbers(self.P, self.bank_d, self.bank_P)

    def pose_numbers(self, aligned: bool) -> PoseNumbers | None:
        """The pose's numbers (:func:`~.pose.pose_numbers`)."""
        return pose_numbers(self.p, self.v, self.q, self.R, self.P, aligned)

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
