"""Robust range updates: NLOS and multipath de-weighted, never locked out for good.

Each range's standardised innovation ``e = ν/√S`` decides its weight ``w`` (the update uses
``R/w``; :meth:`uwbd.fusion.core.eskf.Eskf.sequential_update`):

* ``|e|² > gate``: rejected (the χ² gate, ``gate_probability``);
* otherwise the Geman–McClure weight ``w = (c² / (c² + e²))²``, with ``c`` the scale in σ
  (Bitcraze's robust distance update uses the same ρ function). NLOS only ever adds delay,
  so a range *longer* than predicted (``e > 0``) is judged with ``c_long``, a shorter one
  with the gentler ``c_short``. ``c_long`` is 2.5 unless ``[fusion] nlos_onset_m`` (which
  ``uwbd calibrate-ranges`` fits: the length beyond which a long range is likelier NLOS
  than noise) sets it to that length over ``range_sigma_m``.

A device's own signal quality (0-100, where it sends one) scales ``R`` by
``100/quality`` (at most 10×).

:class:`AnchorStats` keeps, per anchor, how its ranges fared (for the status): accepted,
de-weighted (``w < 0.5``), rejected, and the mean and RMS of the standardised innovation
of accepted ranges (a bias that the range-bias state has not absorbed shows in the mean).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple


@dataclass(frozen=True)
class RobustPolicy:
    enabled: bool = True
    c_long: float = 2.5
    c_short: float = 4.0

    @staticmethod
    def of_onset(enabled: bool, nlos_onset_m: float | None, range_sigma_m: float
                 ) -> RobustPolicy:
        """The policy of a config: ``[fusion] nlos_onset_m`` (``uwbd calibrate-ranges``
        fits it: where a longer range becomes likelier NLOS than noise) as the long side's
        scale in the ranges' σ; without it, the default 2.5 σ."""
        if nlos_onset_m is None:
            return RobustPolicy(enabled)
        return RobustPolicy(enabled, c_long=nlos_onset_m / range_sigma_m)


class RowPolicy(NamedTuple):
    """How :meth:`uwbd.fusion.core.eskf.Eskf.sequential_update` weighs each row of one update:
    ``kinds`` one byte a row — ``r`` a range (the χ² gate ``gate_1``, then the robust
    weight), ``p`` a position-fix axis (the fix as a whole passed its 3-D gate: ``fix_ok``),
    any other a pseudo-measurement (gated, weight 1). A tuple, so that the C core reads it
    without calling back; called as ``policy(i, ν, S)`` it is the reference."""

    kinds: bytes
    gate_1: float
    robust: bool
    c_long: float
    c_short: float
    fix_ok: bool

    @staticmethod
    def of(kinds: bytes, gate_1: float, robust: RobustPolicy, fix_ok: bool) -> RowPolicy:
        return RowPolicy(kinds, gate_1, robust.enabled, robust.c_long, robust.c_short, fix_ok)

    def __call__(self, i: int, nu: float, s: float) -> float:
        kind = self.kinds[i]
        if kind == 0x70:  # "p"
            return 1.0 if self.fix_ok else 0.0
        e2 = nu * nu / s
        if e2 > self.gate_1:
            return 0.0
        if kind != 0x72 or not self.robust:  # "r"
            return 1.0
        e = nu / math.sqrt(s)
        c = self.c_long if e > 0 else self.c_short
        c2 = c * c
        w = c2 / (c2 + e * e)
        return w * w  # not ** 2: libm's pow may round differently from the C core's product


def quality_scale(quality: float | None) -> float:
    """The factor on ``R`` for a range with a device quality (0-100), 1 without one."""
    if quality is None or not math.isfinite(quality):
        return 1.0
    return 100.0 / min(max(quality, 10.0), 100.0)


@dataclass
class AnchorStats:
    accepted: int = 0
    deweighted: int = 0
    rejected: int = 0
    _sum_e: float = 0.0
    _sum_e2: float = 0.0

    def add(self, e: float, weight: float) -> None:
        if weight <= 0.0:
            self.rejected += 1
            return
        self.accepted += 1
        self.deweighted += weight < 0.5
        self._sum_e += e
        self._sum_e2 += e * e

    def as_dict(self) -> dict[str, Any]:
        n = self.accepted
        return {"accepted": n, "deweighted": self.deweighted, "rejected": self.rejected,
                "mean_innovation_sigma": round(self._sum_e / n, 3) if n else None,
                "rms_innovation_sigma": round(math.sqrt(self._sum_e2 / n), 3) if n else None}
