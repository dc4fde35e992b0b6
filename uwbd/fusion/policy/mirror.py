"""Which side of a plane of anchors the tag is on.

Ranges to anchors on one plane (all on the ceiling, all on the floor) fit a tag and its
mirror image through that plane equally well, so least squares lands on whichever side it
starts from. :class:`MirrorSide` holds the two hypotheses:

1. a **hint** settles it: ``tag_side = "below"`` or ``"above"``, or a ``height_range_m``
   that lies on one side of the plane;
2. else the **default**: below anchors mounted 1 m or more above the navigation frame's
   origin (a ground robot or drone under ceiling- or wall-mounted anchors), above anchors
   lower than that (anchors on the floor);
3. and the **data** decide where the anchors are not exactly coplanar: every fix is also
   solved from its mirror image, and the log-likelihood ratio of the two solutions
   (half the difference of their χ², each fix's share clipped at ±3 so that one NLOS range
   cannot decide) is summed. At +``threshold`` the side is resolved; at −``threshold`` it
   flips and the filter restarts on the other side. Until then the side is ``unresolved``
   (said in the status); once flipped, it stays in doubt (no vertical protection level)
   until a hint says it, as a fault on one anchor can flip it and resolve it wrongly.
   Over exactly coplanar anchors the two χ² are equal and the ratio stays at 0: the
   default or hint is kept, and the status says so. A fix counts only
   where the two solutions' ranges differ by more than the errors that do not average out
   could make them (each anchor's delay, the tag's, the slow multipath: ``bias_sigma_m``; all
   ranges together, ``DISTINCT_Z`` σ): over anchors a few centimetres off one plane, a
   constant delay or an NLOS burst otherwise "decides" the side, wrongly as often as not
   (a campaign case, ten anchors within ±5 cm of a 3 m ceiling: the tag put 4.3 m too high
   and said tracking).

Anchors that are not coplanar have no mirror: nothing to decide. The plane may be tilted
(anchors on one wall): its normal, oriented up (on a wall, towards +x or +y), tells the
sides apart, and the default for a wall is the side the normal points to (said unresolved
until the data decide).
"""

from __future__ import annotations

import numpy as np

from uwbd.fusion.core.lsq import LsqFix, coplanar, multilaterate
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array

CEILING_MIN_M = 1.0  # anchors this high or higher: the tag is below them by default
STEP_CLIP = 3.0
DISTINCT_Z = 3.0  # the sides' predicted ranges this many bias σ apart (all ranges together)
WALL_NORMAL_Z = 0.5  # a plane whose normal is flatter than this is a wall: no floor rule


class MirrorSide:
    def __init__(self, anchors_m: Array, hint: str = "auto",
                 height_range_m: tuple[float, float] | None = None,
                 threshold: float = 10.0, bias_sigma_m: float = 0.0, *, core: Core) -> None:
        self._core = core  # the mirror image's least squares: C, or the reference (None)
        # what the ranges' errors that do not average out may be (each anchor's delay, the
        # tag's, the slow multipath), 1 σ: a mirror image they could explain tells nothing
        self.bias_sigma_m = bias_sigma_m
        if hint not in ("auto", "below", "above"):
            raise ValueError(f"tag side must be auto, below or above, got {hint!r}")
        self.ambiguous = len(anchors_m) >= 3 and coplanar(anchors_m)
        self.threshold = threshold
        self.llr = 0.0
        self.flipped = False
        self.flips = 0  # how often the data flipped the side
        self.plane_z = float(np.mean(anchors_m[:, 2])) if len(anchors_m) else 0.0
        # the plane through the anchors: centroid and unit normal, pointing up (for a wall,
        # "above" is the side the normal points to)
        self.centroid = anchors_m.mean(axis=0) if len(anchors_m) else np.zeros(3)
        self.normal = np.array([0.0, 0.0, 1.0])
        if len(anchors_m) >= 3:
            n = np.linalg.svd(anchors_m - self.centroid)[2][-1]
            largest = int(np.argmax(np.abs(n[:2]))) if abs(n[2]) < WALL_NORMAL_Z else 2
            self.normal = -n if n[largest] < 0 else n
        self.decided_by = "no mirror" if not self.ambiguous else "default"
        wall = abs(self.normal[2]) < WALL_NORMAL_Z
        sign = 1 if wall else (-1 if self.plane_z >= CEILING_MIN_M else 1)
        if hint != "auto":
            sign, self.decided_by = (-1 if hint == "below" else 1), "configured"
        elif height_range_m is not None and not wall:
            lo, hi = height_range_m
            if hi < self.plane_z:
                sign, self.decided_by = -1, "configured height range"
            elif lo > self.plane_z:
                sign, self.decided_by = 1, "configured height range"
        self.sign = sign
        self.resolved = not self.ambiguous or self.decided_by != "default"

    @property
    def unresolved(self) -> bool:
        return not self.resolved

    @property
    def side_doubted(self) -> bool:
        """The data have flipped the side away from the default: a fault on one anchor can
        make the mirror image fit better, and then resolve the side on the wrong one (a
        campaign case: a ground robot put 5 m above a 3.2 m ceiling), so the side stays in
        doubt until a hint (``tag_side``, ``height_range_m``) says it."""
        return self.flips > 0

    def side_of(self, x: Array) -> float:
        """Signed distance of ``x`` from the plane (+: above)."""
        return float((x - self.centroid) @ self.normal)

    def reflect(self, x: Array) -> Array:
        return x - 2.0 * self.side_of(x) * self.normal

    def start_point(self) -> Array:
        """Where least squares starts without a better guess: 1 m off the plane on the
        current side."""
        return self.centroid + self.sign * self.normal

    def weigh(self, anchors: Array, ranges: Array, fix: LsqFix, sigma_m: float,
              fixed_z: float | None) -> None:
        """Add one fix's evidence (solved on the current side) for the side."""
        if self.resolved or fixed_z is not None or len(ranges) < 4:
            return
        other = multilaterate(anchors, ranges, sigma_m, self.reflect(fix.position_m), None,
                              side=-self.sign, core=self._core)
        if other is None or self.side_of(other.position_m) * self.sign > 0:
            return  # it fell back to this side: this fix does not tell the two apart
        if self.bias_sigma_m > 0:  # the two sides' ranges apart by less than the biases
            apart = other.residuals_m - fix.residuals_m
            if float(np.nansum(apart**2)) < DISTINCT_Z**2 * self.bias_sigma_m**2:
                return
        chi2_here = float(np.nansum(fix.residuals_m**2)) / sigma_m**2
        chi2_there = float(np.nansum(other.residuals_m**2)) / sigma_m**2
        self.llr += float(np.clip((chi2_there - chi2_here) / 2, -STEP_CLIP, STEP_CLIP))
        if self.llr >= self.threshold:
            self.resolved, self.decided_by = True, "ranges"
        elif self.llr <= -self.threshold:
            self.sign, self.llr, self.flipped = -self.sign, 0.0, True
            self.flips += 1
            self.decided_by = "ranges (flipped)"

    def take_flip(self) -> bool:
        """True once after the data flipped the side: the filter must restart."""
        flipped, self.flipped = self.flipped, False
        return flipped
