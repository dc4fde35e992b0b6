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
   (said in the status). Over exactly coplanar anchors the two χ² are equal and the ratio
   stays at 0: the default or hint is kept, and the status says so.

Anchors that are not coplanar have no mirror: nothing to decide.
"""

from __future__ import annotations

import numpy as np

from uwbd.fusion.lsq import LsqFix, coplanar, multilaterate
from uwbd.fusion.rotation import Array

CEILING_MIN_M = 1.0  # anchors this high or higher: the tag is below them by default
STEP_CLIP = 3.0


class MirrorSide:
    def __init__(self, anchors_m: Array, hint: str = "auto",
                 height_range_m: tuple[float, float] | None = None,
                 threshold: float = 10.0) -> None:
        if hint not in ("auto", "below", "above"):
            raise ValueError(f"tag side must be auto, below or above, got {hint!r}")
        self.ambiguous = len(anchors_m) >= 3 and coplanar(anchors_m)
        self.threshold = threshold
        self.llr = 0.0
        self.flipped = False
        self.plane_z = float(np.mean(anchors_m[:, 2])) if len(anchors_m) else 0.0
        self.decided_by = "no mirror" if not self.ambiguous else "default"
        sign = -1 if self.plane_z >= CEILING_MIN_M else 1
        if hint != "auto":
            sign, self.decided_by = (-1 if hint == "below" else 1), "configured"
        elif height_range_m is not None:
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

    def weigh(self, anchors: Array, ranges: Array, fix: LsqFix, sigma_m: float,
              fixed_z: float | None) -> None:
        """Add one fix's evidence (solved on the current side) for the side."""
        if self.resolved or fixed_z is not None or len(ranges) < 4:
            return
        mirror_x0 = fix.position_m.copy()
        mirror_x0[2] = 2 * self.plane_z - mirror_x0[2]
        other = multilaterate(anchors, ranges, sigma_m, mirror_x0, None, side=-self.sign)
        if other is None or (other.position_m[2] - self.plane_z) * self.sign > 0:
            return  # it fell back to this side: this fix does not tell the two apart
        chi2_here = float(np.nansum(fix.residuals_m**2)) / sigma_m**2
        chi2_there = float(np.nansum(other.residuals_m**2)) / sigma_m**2
        self.llr += float(np.clip((chi2_there - chi2_here) / 2, -STEP_CLIP, STEP_CLIP))
        if self.llr >= self.threshold:
            self.resolved, self.decided_by = True, "ranges"
        elif self.llr <= -self.threshold:
            self.sign, self.llr, self.flipped = -self.sign, 0.0, True
            self.decided_by = "ranges (flipped)"

    def take_flip(self) -> bool:
        """True once after the data flipped the side: the filter must restart."""
        flipped, self.flipped = self.flipped, False
        return flipped
