"""How one sequential update weighs its rows: the χ² gate and the robust weight as numbers.

The policy (:mod:`uwbd.fusion.policy.robust`) sets the numbers; the core applies them to each
row's innovation. :class:`RowPolicy` is a tuple so that the C core reads it without calling
back (setup.py generates its fields' places and the row kinds for the C core from this file);
called as ``policy(i, ν, S)`` it is the reference the tests hold the C core to.
"""

from __future__ import annotations

import math
from typing import NamedTuple


class Row(NamedTuple):
    """One scalar of a sequential update: innovation, its variance, the weight it was fused
    with (0: not fused), and whether it was skipped as numerically impossible."""

    innovation: float
    variance: float
    weight: float
    numerical: bool


RawRow = tuple[float, float, float, bool]  # a Row's fields as the C core returns them


# a row's kind, as one byte of RowPolicy.kinds: the first letter of the measurement's kind
RANGE_ROW, POSITION_ROW = ord("r"), ord("p")


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

    def __call__(self, i: int, nu: float, s: float) -> float:
        kind = self.kinds[i]
        if kind == POSITION_ROW:
            return 1.0 if self.fix_ok else 0.0
        e2 = nu * nu / s
        if e2 > self.gate_1:
            return 0.0
        if kind != RANGE_ROW or not self.robust:
            return 1.0
        e = nu / math.sqrt(s)
        c = self.c_long if e > 0 else self.c_short
        c2 = c * c
        w = c2 / (c2 + e * e)
        return w * w  # not ** 2: libm's pow may round differently from the C core's product


def full_weight(i: int, nu: float, s: float) -> float:
    """Every row at weight 1 (no gate)."""
    return 1.0
