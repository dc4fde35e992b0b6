"""The filter's state on the C core: :class:`CoreEskf`, the operations of
:class:`~uwbd.fusion.core.eskf.Eskf` on numbers that the C type ``_core.State`` owns
(``uwbd/fusion/core/_state.c``), and :func:`new_eskf`, which makes one or the other.

The state is read as numpy views of the C type's memory (``p v q b_g b_a b_r P last_dx``, no
copies, read-only); it changes through the operations alone. Eskf, in pure Python, is the
reference: ``UWBD_PURE_PYTHON=1`` runs it, and tests/test_core.py holds the two together.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from uwbd.fusion.core.bank import SeparationNumbers, bank_variances
from uwbd.fusion.core.eskf import Eskf, Vector
from uwbd.fusion.core.layout import N_CORE, NOMINAL, NOMINAL_AUX
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.noise import GRAVITY_MPS2, ImuNoise, process_noise
from uwbd.fusion.core.pose import PoseNumbers
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.weights import RawRow, Row, RowPolicy


def new_eskf(core: Core, p: Vector, v: Vector, q: Vector, P0: Array, noise: ImuNoise,
             n_range_bias: int = 0, **kwargs: Any) -> Eskf:
    """A filter state on ``core`` (the C core), or with None the pure-Python reference;
    the other arguments are :class:`Eskf`'s."""
    if core is None:
        return Eskf(p, v, q, P0, noise, n_range_bias, **kwargs)
    return CoreEskf(p, v, q, P0, noise, n_range_bias, core=core, **kwargs)


class CoreEskf(Eskf):
    """:class:`Eskf`'s operations on the C core's state (see module doc). Its read-only
    helpers (``R``, the yaw and tilt σ) are Eskf's, reading the views."""

    fuses_ranges = True

    def __init__(self, p: Vector, v: Vector, q: Vector, P0: Array, noise: ImuNoise,
                 n_range_bias: int = 0, b_g: Vector = (0.0, 0.0, 0.0),
                 b_a: Vector = (0.0, 0.0, 0.0), aux_tau_s: Array | None = None,
                 aux_sigma: Array | None = None, gravity_mps2: float = GRAVITY_MPS2,
                 b_r: Vector | None = None, bank: Sequence[int] = (),
                 bank_var: Array | None = None, *, core: Core) -> None:
        if core is None:
            raise RuntimeError("CoreEskf: no C core given (uwbd --version says whether it "
                               "is built)")
        n = N_CORE + n_range_bias
        P0 = np.ascontiguousarray(P0, dtype=float)
        if P0.shape != (n, n):
            raise ValueError(f"P0 must be {n}x{n}, got {P0.shape}")
        b_r = np.zeros(n_range_bias) if b_r is None else np.asarray(b_r, dtype=float)
        if b_r.shape != (n_range_bias,):
            raise ValueError(f"b_r must hold {n_range_bias} numbers, got {b_r.shape}")
        q_rate, tau, var = process_noise(noise, n_range_bias, aux_tau_s, aux_sigma)
        self.n = n
        self.noise = noise
        self.gravity_mps2 = float(gravity_mps2)
        self._state = self.core_state = state = core.State(
            [float(c) for c in p], [float(c) for c in v], [float(c) for c in q],
            [float(c) for c in b_g], [float(c) for c in b_a], b_r.tolist(), P0,
            q_rate.tolist(), tau.tolist(), var.tolist(), self.gravity_mps2,
            [int(a) for a in bank], bank_variances(bank_var, len(bank), n))
        x = np.frombuffer(state, dtype=float)  # the C type's memory, read-only
        m = n_range_bias
        (self.p, self.v, self.q, self.b_g, self.b_a) = (
            x[start:stop] for start, stop in NOMINAL.values())
        self.b_r = x[NOMINAL_AUX:NOMINAL_AUX + m]
        self.P = x[NOMINAL_AUX + m:NOMINAL_AUX + m + n * n].reshape(n, n)
        end = NOMINAL_AUX + m + n * n + n
        self.last_dx = x[end - n:end]
        self.bank = tuple(state.bank)
        k = len(self.bank)
        self.bank_d = x[end:end + k * n].reshape(k, n)
        self.bank_P = x[end + k * n:].reshape(k, n, n)
        self._clamp_key: tuple[Array, float] | None = None
        self._clamp_limit = np.zeros(0)
        # the hot operations, bound once
        self._predict = state.predict
        self._update = state.update
        self._fuse_ranges = state.fuse_ranges

    # the class's attribute is the C type's (a property there)
    @property
    def keep_transition(self) -> bool:
        return bool(self._state.keep_transition)

    @keep_transition.setter
    def keep_transition(self, keep: bool) -> None:
        self._state.keep_transition = keep

    def predict(self, acc_b: Vector, gyro_b: Vector, dt: float) -> None:
        self._predict(acc_b, gyro_b, dt)

    def propagate(self) -> None:
        self._state.propagate()

    @property
    def interval_s(self) -> float:
        return float(self._state.interval_s)

    def take_epoch(self, with_phi: bool = True
                   ) -> tuple[Array | None, tuple[float, float, float]]:
        core_phi, decay, dv = self._state.take_epoch(with_phi)
        Phi = None
        if core_phi is not None:
            Phi = np.eye(self.n)
            Phi[:N_CORE, :N_CORE] = np.array(core_phi).reshape(N_CORE, N_CORE)
            Phi[N_CORE:, N_CORE:] = np.diag(decay)
        return Phi, dv

    def rotate_heading(self, dpsi: float, yaw_sigma_rad: float) -> None:
        self._state.rotate_heading(dpsi, yaw_sigma_rad)

    def coast(self, dt: float, accel_sigma_mps2: float, yaw_rate_sigma_rps: float,
              tilt_rate_sigma_rps: float) -> None:
        self._state.coast(dt, accel_sigma_mps2, yaw_rate_sigma_rps, tilt_rate_sigma_rps)

    def sequential_update(self, H: Array, y: Array, R: Array,
                          decide: Callable[[int, float, float], float] | RowPolicy,
                          considered: slice | None = None,
                          ids: Sequence[int] | None = None) -> list[Row]:
        c0, c1 = _columns(considered, self.n)
        rows = self._update(np.ascontiguousarray(H, dtype=float),
                            np.ascontiguousarray(y, dtype=float),
                            np.ascontiguousarray(R, dtype=float), decide, c0, c1, ids)
        return [Row(*r) for r in rows]

    def fuse_ranges(self, lever_m: Array, anchors: Array, ranges: Array, var: Array,
                    columns: tuple[tuple[int, ...], ...], lever_columns: tuple[int, ...],
                    extra: tuple[Array, Array, Array], decide: RowPolicy,
                    considered: slice | None, ids: Sequence[int] = ()
                    ) -> list[RawRow | None] | None:
        c0, c1 = _columns(considered, self.n)
        H, y, R = extra
        rows: list[RawRow | None] = self._fuse_ranges(
            lever_m, np.ascontiguousarray(anchors, dtype=float),
            np.ascontiguousarray(ranges, dtype=float), np.ascontiguousarray(var, dtype=float),
            columns, lever_columns, np.ascontiguousarray(H, dtype=float),
            np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(R, dtype=float), decide,
            c0, c1, ids)
        return rows

    def fuse_period(self, front: Any, order: bytes, samples: list[Any], ranges: list[Any],
                    lever_m: list[float], lever_columns: tuple[int, ...], decide: RowPolicy,
                    max_core_sigma: Array, max_aux_sigma: float,
                    clock: tuple[int, int, float, float, float], last_imu: Sequence[float]
                    ) -> tuple[int, str | None, list[tuple[float, ...]], list[RawRow | None],
                               int, int, tuple[float, ...], int, bool]:
        """A pose period's items in one call (``_core.State.fuse_period``; the policy's
        side: :mod:`uwbd.fusion.policy.period`), P clamped as :meth:`clamp_covariance`."""
        out: Any = self._state.fuse_period(
            front, order, samples, ranges, lever_m, lever_columns, decide,
            self._clamp_limit_of(max_core_sigma, max_aux_sigma), clock, last_imu)
        return out

    def inject(self, dx: Array) -> None:
        """(On the C core a correction enters only through an update.)"""
        raise TypeError("CoreEskf.inject: the C core injects inside its updates")

    def clamp_covariance(self, max_core_sigma: Array, max_aux_sigma: float) -> bool:
        return bool(self._state.clamp(self._clamp_limit_of(max_core_sigma, max_aux_sigma)))

    def widen(self, states: slice, sigma_factor: float) -> None:
        c0, c1 = _columns(states, self.n)
        self._state.widen(c0, c1, sigma_factor)

    def add_variances(self, d: Array) -> None:
        self._state.add_variances(np.asarray(d, dtype=float).tolist())

    def set_covariance(self, P: Array) -> None:
        self._state.set_covariance(np.ascontiguousarray(P, dtype=float))
        self.bank_resets += 1

    def move_to(self, p: Vector, v: Vector) -> None:
        self._state.move_to([float(c) for c in p], [float(c) for c in v])
        self.bank_resets += 1

    def adopt(self, k: int) -> None:
        self._state.adopt(k)
        self.bank_resets += 1

    def restart_member(self, k: int) -> None:
        self._state.restart(k)

    def separation_numbers(self) -> SeparationNumbers:
        return self._state.separation_numbers()

    def pose_numbers(self, aligned: bool) -> PoseNumbers | None:
        numbers: PoseNumbers | None = self._state.pose_numbers(aligned)
        return numbers


def _columns(states: slice | None, n: int) -> tuple[int, int]:
    """A slice of states as the C core's [c0, c1) (None: none)."""
    if states is None:
        return 0, 0
    c0, c1, step = states.indices(n)
    if step != 1:
        raise ValueError("states: a slice of step 1")
    return c0, max(c0, c1)
