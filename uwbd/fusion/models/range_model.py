"""The tag antenna's direction-dependent delay (docs/ekf.md §4, range model).

A UWB antenna's group delay depends on the direction the signal leaves or arrives from. On
DW1000-class tags it is the largest calibratable range error: centimetres to a decimetre,
systematic, and not noise a filter can average away. It is modelled as real spherical
harmonics of the ray's direction in the tag's axes::

    range = |p_antenna − a| + Σ_{l=1..L} Σ_{m=−l..l} c_lm Y_lm(u) + offsets + noise,
    u = C_tbᵀ Rᵀ (p_antenna − a) / |p_antenna − a|      (anchor → tag, tag axes)

with ``C_tb`` the tag's mounting (tag axes → body axes). ``Y_lm`` are normalised so that each
has a mean square of 1 over the sphere (4π-normalised: the orthonormal ones × √(4π)), so a
coefficient is the RMS delay of its term over all directions, in metres. Degree 0 (a
constant) is not part of the model: the filter's delay states take it.

Each anchor's own antenna delay is a constant of the device (it carries from one room to
another with the unit: measured 1.6 cm RMS between the two INRoL rooms); a calibration
gives it, and the ranges are corrected by it from the first one.

A DW1000's range also grows with the distance beyond the distance itself: its first-path
timing depends on the received power, which falls 20 dB a decade. The model takes it as
``k ln(d / 1 m)`` (``log_distance_m`` = k ≥ 0: the delay grows with the distance; an
anchor's delay is then its delay at 1 m; constant below ``MIN_LOG_DISTANCE_M``). It needs no
attitude, so it comes off with the anchors' delays, from the first range, with the
direction term still in the range (which scales that term by ``1/(1 + k/d)``: 6 mm of a
5 cm term at 1 m). On the
INRoL hardware ``k`` ≈ 0.12 m: a range at 4 m carries 17 cm more delay than one at 1 m. Left
in, it stretches the solution away from the room's centre by about 5 %.

Each anchor's antenna has a direction-dependent delay too, common to the units of one
model: ``Σ c'_lm Y_lm(u_a)`` of the same ray in the anchor's axes (``u_a = C_anᵀ (p_antenna
− a) / |…|``, ``C_an`` the anchor's orientation that ``[anchors]`` gives in the table form).
It needs the tag's position only, not its attitude: the filter takes it off each range at
the prior position (its position Jacobian, about c'/d, is left out), from the start of
tracking; anchors given without an orientation take none.

Degree 1 is exactly a shift of the antenna's phase centre: ``Σ_m c_1m Y_1m(u) = δ·u`` with
``δ = √3 (c_11, c_1−1, c_10)`` (tag x, y, z), and ``|d + R δ| ≈ |d| + δ·u``. The filter
applies it as a lever arm of ``lever + C_tb δ``, so its Jacobian comes free. Higher degrees
are subtracted from the ranges at the prior attitude (their attitude Jacobian is left out:
a few millimetres per radian on the recordings measured).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from uwbd.fusion.core.rotation import Array

Vector = Sequence[float] | Array
MAX_DEGREE = 3
MIN_LOG_DISTANCE_M = 0.1  # the distance term's log is taken of no less (a range near 0)
MAX_NEWTON_STEPS = 8
LOG_FLOOR = math.log(MIN_LOG_DISTANCE_M)
SQRT3 = math.sqrt(3.0)
IDENTITY3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def n_coefficients(degree: int) -> int:
    """Coefficients of degrees 1..``degree``: 3, 8, 15."""
    return (degree + 1) ** 2 - 1


def harmonics(x: Any, y: Any, z: Any, degree: int) -> list[Any]:
    """The 4π-normalised real spherical harmonics of the unit vector (x, y, z) for degrees
    1..``degree``, each degree's in the order m = −l..l: floats, or arrays of them."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"degree {degree}: expected 0..{MAX_DEGREE}")
    s3 = SQRT3
    out = [s3 * y, s3 * z, s3 * x] if degree >= 1 else []
    if degree >= 2:
        s15 = math.sqrt(15.0)
        out += [s15 * x * y, s15 * y * z, math.sqrt(5.0) / 2 * (3 * z * z - 1),
                s15 * x * z, s15 / 2 * (x * x - y * y)]
    if degree >= 3:
        a, b, c = math.sqrt(35 / 8), math.sqrt(105.0), math.sqrt(21 / 8)
        out += [a * y * (3 * x * x - y * y), b * x * y * z, c * y * (5 * z * z - 1),
                math.sqrt(7.0) / 2 * z * (5 * z * z - 3), c * x * (5 * z * z - 1),
                b / 2 * z * (x * x - y * y), a * x * (x * x - 3 * y * y)]
    return out


def basis(u: Array, degree: int) -> Array:
    """:func:`harmonics` of unit vectors ``u`` (n×3): (n, :func:`n_coefficients`)."""
    cols = harmonics(u[:, 0], u[:, 1], u[:, 2], degree)
    return np.stack(cols, axis=1) if cols else np.zeros((len(u), 0))


@dataclass(frozen=True)
class RangeModel:
    """The ``[range_model]`` section: the tag's direction term (degree 0: none), the
    anchors' calibrated antenna delays (none: the filter's delay states estimate them) and
    the distance term (k = 0: none)."""

    degree: int = 0
    coefficients_m: tuple[float, ...] = ()  # degrees 1..degree, each m = −l..l
    tag_mounting: tuple[tuple[float, float, float], ...] = IDENTITY3  # tag axes -> body
    # (anchor id, delay m): taken off that anchor's every range, before anything else
    anchor_delays_m: tuple[tuple[int, float], ...] = ()
    log_distance_m: float = 0.0  # k ≥ 0 of the distance term k ln(d / 1 m); 0: none
    # the anchors' own direction term (degree 0: none), common to the units, of the ray in
    # each anchor's axes; applied to the anchors whose axes [anchors] gives (id, rows:
    # anchor axes -> navigation frame)
    anchor_degree: int = 0
    anchor_coefficients_m: tuple[float, ...] = ()
    anchor_axes: tuple[tuple[int, tuple[tuple[float, float, float], ...]], ...] = ()

    def __post_init__(self) -> None:
        for what, degree, c in (("degree", self.degree, self.coefficients_m),
                                ("anchor degree", self.anchor_degree,
                                 self.anchor_coefficients_m)):
            if len(c) != n_coefficients(degree):
                raise ValueError(f"{what} {degree} takes {n_coefficients(degree)} "
                                 f"coefficients, got {len(c)}")

    @property
    def enabled(self) -> bool:
        return self.degree > 0

    @functools.cached_property
    def _delays(self) -> dict[int, float]:
        return dict(self.anchor_delays_m)

    @functools.cached_property
    def _anchor_axes(self) -> dict[int, Array]:
        return {a: np.array(rows, dtype=float) for a, rows in self.anchor_axes}

    def anchor_term_m(self, ids: Sequence[int], anchors_m: Array, antenna_m: Array) -> Array:
        """Each range's anchor direction term for the antenna at ``antenna_m`` (0 for an
        anchor without axes, and for every one at anchor degree 0)."""
        out = np.zeros(len(ids))
        if not self.anchor_degree:
            return out
        axes, c = self._anchor_axes, self.anchor_coefficients_m
        for i, a in enumerate(ids):
            C = axes.get(a)
            if C is None:
                continue
            x, y, z = (C.T @ (antenna_m - anchors_m[i])).tolist()  # anchor -> tag, its axes
            n = math.sqrt(x * x + y * y + z * z) or 1.0
            out[i] = sum(k * h for k, h in zip(
                c, harmonics(x / n, y / n, z / n, self.anchor_degree), strict=True))
        return out

    @property
    def corrects_ranges(self) -> bool:
        """Whether :meth:`corrected_m` changes a range."""
        return bool(self.anchor_delays_m) or self.log_distance_m != 0.0

    def corrected_m(self, ids: Sequence[int], ranges_m: Sequence[float]) -> list[float]:
        """The ranges less what needs no attitude, before anything else: each anchor's
        delay, then the distance term (:meth:`without_distance_term`). In floats: a
        message holds one range or a few."""
        delays = self._delays
        if not self.log_distance_m:
            return [r - delays.get(a, 0.0) for a, r in zip(ids, ranges_m, strict=True)]
        distance = self.distance_m
        return [distance(r - delays.get(a, 0.0)) for a, r in zip(ids, ranges_m, strict=True)]

    def without_distance_term(self, ranges_m: Array) -> Array:
        """``ranges_m`` (their anchors' delays already off) less the distance term: the
        ``d`` whose ``d + k ln max(d, D)`` is the range (``D`` = ``MIN_LOG_DISTANCE_M``).
        With k ≥ 0 that is increasing, so each range has one: below ``D + k ln D`` the
        constant ``k ln D`` comes off; above it, one fixed-point step from ``r``, then
        Newton's (the function is concave: they climb to the root from below) until the
        next would move it less than a micrometre: one at k ≈ 0.1 m beyond 1 m, up to six
        for k = 0.5 m near D."""
        return np.array([self.distance_m(r) for r in ranges_m.tolist()])

    def distance_m(self, r: float) -> float:
        """The distance a range ``r`` (its anchor's delay off) stands for: see
        :meth:`without_distance_term`."""
        k, floor, log = self.log_distance_m, MIN_LOG_DISTANCE_M, math.log
        if not r > floor + k * LOG_FLOOR:  # (NaN too: it stays NaN)
            return r - k * LOG_FLOOR
        d = max(r - k * log(r), floor) if r > floor else floor  # a fixed-point step
        for _ in range(MAX_NEWTON_STEPS):
            step = (d + k * log(d) - r) / (1.0 + k / d)
            d = max(d - step, floor)
            if k * step * step < 2e-6 * d * d:  # the next step's error, k s²/2d², under 1 µm
                break
        return d

    def delay_m(self, anchor: Sequence[int] | npt.NDArray[np.int64], u_tag: Array,
                distance_m: Array, u_anchor: Array | None = None) -> Array:
        """The whole model's delay of each range: its anchor's delay, the distance term, the
        tag's direction term (rays ``u_tag``, tag axes; n×3) and the anchors' (rays
        ``u_anchor`` in the anchors' axes, NaN rows where an anchor has none)."""
        delays = self._delays
        out = np.array([delays.get(int(a), 0.0) for a in anchor], dtype=float)
        if self.log_distance_m:
            out += self.log_distance_m * np.log(np.maximum(distance_m, MIN_LOG_DISTANCE_M))
        if self.enabled:
            out += basis(u_tag, self.degree) @ np.array(self.coefficients_m)
        if self.anchor_degree and u_anchor is not None:
            term = basis(np.nan_to_num(u_anchor), self.anchor_degree) @ np.array(
                self.anchor_coefficients_m)
            out += np.where(np.isnan(u_anchor[:, 0]), 0.0, term)
        return out

    def phase_centre_m(self) -> Array:
        """The degree-1 part as a phase-centre offset, body axes."""
        if not self.enabled:
            return np.zeros(3)
        c_y, c_z, c_x = self.coefficients_m[:3]
        return np.array(self.tag_mounting) @ (SQRT3 * np.array([c_x, c_y, c_z]))

    def higher_delay_m(self, q_wxyz: Vector, p_m: Vector, lever_m: Vector,
                       anchors_m: Array) -> Array:
        """The delay of degrees 2..L of each range (m) for the pose (``q_wxyz`` body to
        navigation, ``p_m``) with the antenna at ``lever_m`` (body axes); zeros at degree 1.
        In floats: an epoch holds one range or a few."""
        if self.degree < 2:
            return np.zeros(len(anchors_m))
        w, x, y, z = q_wxyz
        R = ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
             (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
             (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))
        p_ant = [p_m[i] + R[i][0] * lever_m[0] + R[i][1] * lever_m[1] + R[i][2] * lever_m[2]
                 for i in range(3)]
        (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = self.tag_mounting
        out = []
        higher = self.coefficients_m[3:]
        for a in anchors_m.tolist():
            d = [p_ant[0] - a[0], p_ant[1] - a[1], p_ant[2] - a[2]]
            b = [R[0][j] * d[0] + R[1][j] * d[1] + R[2][j] * d[2] for j in range(3)]  # Rᵀ d
            u = (m00 * b[0] + m10 * b[1] + m20 * b[2], m01 * b[0] + m11 * b[1] + m21 * b[2],
                 m02 * b[0] + m12 * b[1] + m22 * b[2])  # C_tbᵀ Rᵀ d
            n = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) or 1.0
            terms = harmonics(u[0] / n, u[1] / n, u[2] / n, self.degree)[3:]
            out.append(sum(c * h for c, h in zip(higher, terms, strict=True)))
        return np.array(out)
