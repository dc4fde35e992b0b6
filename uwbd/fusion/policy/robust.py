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
from typing import Any


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
