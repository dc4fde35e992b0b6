"""The survey's settings, results and constants, and where the output frame puts an anchor
(:mod:`uwbd.tools.survey`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from uwbd.fusion.core.rotation import Array

Vec3 = tuple[float, float, float]


WINDOW_S = 0.2  # asynchronous single ranges: one tag position this often


MIN_EPOCH_RANGES = 4  # an epoch with 3 ranges fits any anchors: it says nothing about them


# the tag's ranges: arctan (redescending: a range 6 σ off weighs 1/80 of a good one; NLOS),
# quadratic to about this many σ
ROBUST_SCALE = 2.0


MAX_EVALUATIONS = 200


TRUST = 2.0  # a direction is moved where the ranges fix it to half the prior's σ or better


MAD_TO_SIGMA = 1.4826


MEDIAN_EFFICIENCY = 1.2533  # the standard error of a median is this times the mean's


PAIR_SIGMA_FLOOR_M = 0.002  # a pair's σ never below 2 mm (its ranges are mm integers)


COPLANAR_M = 0.3  # anchors this close to one plane (RMS): their heights are held


SIDE_TOLERANCE_M = 0.05  # an anchor this close to the x axis is on neither side


SIDE_TOLERANCE_RAD = 0.01  # ... or this close in angle (a long baseline)


class SurveyError(ValueError):
    """What the user asked for cannot be surveyed (one line: the CLI's exit 2)."""


@dataclass(frozen=True)
class Gauge:
    """The frame the anchors are given in: ``origin`` at (0, 0), ``x_axis`` on +x,
    ``y_side`` on the +y side; ``origin`` ``None``: the config's frame (priors only)."""

    origin: int | None = None
    x_axis: int | None = None
    y_side: int | None = None

    @property
    def user(self) -> bool:
        return self.origin is not None


@dataclass(frozen=True)
class Settings:
    gauge: Gauge = Gauge()
    heights_m: Mapping[int, float] = field(default_factory=dict)  # held exactly
    prior_sigma_m: float = 0.2
    range_sigma_m: float = 0.1
    range_offsets: bool = False
    offset_sigma_m: float = 0.1
    tag_side: str = "auto"
    height_range_m: tuple[float, float] | None = None
    max_range_m: float = 100.0
    window_s: float = WINDOW_S


@dataclass(frozen=True)
class PairRange:
    """One anchor pair's repeated ranges, reduced: median, its standard error (1.2533 ×
    1.4826 MAD / √n), and how many were more than 5 robust σ off the median."""

    anchor_a: int
    anchor_b: int
    n: int
    median_m: float
    sigma_m: float
    outliers: int


@dataclass(frozen=True)
class AnchorEstimate:
    """``position_m`` in the output frame, ``sigma_m`` its 1-σ per axis (0 where the gauge
    or ``--height`` holds it); ``configured_m`` as in the config (its frame), ``prior_m``
    the config carried into the output frame; ``surveyed``: ranges reached it."""

    anchor: int
    position_m: Vec3
    sigma_m: Vec3
    configured_m: Vec3 | None
    prior_m: Vec3 | None
    surveyed: bool
    range_offset_m: float | None = None
    range_offset_sigma_m: float | None = None

    @property
    def change_m(self) -> Vec3 | None:
        """From the configured position (carried into the output frame) to the surveyed
        one."""
        if self.prior_m is None:
            return None
        p, c = self.position_m, self.prior_m
        return (p[0] - c[0], p[1] - c[1], p[2] - c[2])


@dataclass
class Survey:
    anchors: dict[int, AnchorEstimate]
    source: str  # "anchor-to-anchor ranges" or "tag ranges" (+ pairs)
    gauge: str
    tag_ranges: int = 0
    tag_positions: int = 0
    pairs: list[PairRange] = field(default_factory=list)
    residual_rms_m: float = math.nan  # tag ranges: robust RMS (1.4826 MAD), m
    sigma0: float = 1.0
    downweighted: int = 0  # tag ranges more than 3 σ off at the solution
    layout_sigma_m: float = math.nan  # RMS 3-D 1-σ of the anchors relative to each other
    frame_sigma_m: float = math.nan  # RMS 3-D 1-σ of where the layout sits (soft gauge)
    iterations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    # the config's frame -> the output frame: p' = R(turn) (p - shift); zero in the config's
    frame_shift_m: tuple[float, float] = (0.0, 0.0)
    frame_turn_deg: float = 0.0
    user_frame: bool = False  # --origin/--x-axis: x, y and the heading held, not soft

    def positions(self) -> dict[int, Vec3]:
        return {a: e.position_m for a, e in sorted(self.anchors.items())}


def frame_of(origin: Array, x_point: Array) -> tuple[Array, Array]:
    """The rotation (about z) and translation taking ``origin`` to (0, 0, z) and
    ``x_point`` onto the +x axis: p' = R (p - t)."""
    heading = math.atan2(x_point[1] - origin[1], x_point[0] - origin[0])
    c, s = math.cos(heading), math.sin(heading)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.array([origin[0], origin[1], 0.0])
    return R, t


def side_of(p: Array, x_point: Array) -> int:
    """+1, -1: which side of the +x axis ``p`` is on (in the gauge frame); 0: too close to
    it to tell (5 cm, or 0.01 rad seen from the middle of origin and ``x_point``)."""
    off_axis = abs(float(p[0]) - float(x_point[0]) / 2)
    if abs(p[1]) < max(SIDE_TOLERANCE_M, SIDE_TOLERANCE_RAD * off_axis):
        return 0
    return 1 if p[1] > 0 else -1
