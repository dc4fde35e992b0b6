"""Does the vehicle move along its forward axis? A mounting turned about the vertical, for a
ground vehicle (docs/ekf.md §6).

The non-holonomic constraint (``[fusion] nhc``) says a ground vehicle's body velocity has
no sideways part. A mounting typed wrong by a turn about z does not stop the filter: the
heading alignment turns the state so that the ranges agree, and the body axes are then
turned against the vehicle by the same angle; the vehicle moves along the body's +y (a
90° error), and every NHC row is rejected. The direction of travel in body axes,
``ψ = atan2(v_y, v_x)`` while moving, is therefore the mounting's error. It is averaged as
an axis (``2ψ``: driving backwards is driving along the same axis), so a sensor turned by
180° is not seen, and a consistent ``ψ`` over ``MIN_SAMPLES`` of the last ``WINDOW``
moving samples, more than ``MAX_ERROR_DEG`` off, is a finding: the health fault
``mounting_inconsistent`` and the status's ``mounting_finding``.
"""

from __future__ import annotations

import collections
import math

MIN_SPEED_MPS = 0.5  # slower, the direction of travel is mostly the velocity's noise
WINDOW = 200  # moving samples kept (about 20 s at the constraints' 10 Hz)
MIN_SAMPLES = 50
MIN_AGREEMENT = 0.8  # the mean resultant length of the axes: 1 is always the same axis
MAX_ERROR_DEG = 20.0  # a crab angle this large is no wheel slip: the mounting


class MountingYaw:
    """The direction of travel in body axes, and what it says of ``imu.mounting``."""

    def __init__(self) -> None:
        self._axes: collections.deque[tuple[float, float]] = collections.deque(maxlen=WINDOW)
        self._sum_c = self._sum_s = 0.0
        self.error_deg: float | None = None  # the finding: the direction of travel, degrees

    def add(self, vx_b: float, vy_b: float) -> None:
        """One body velocity (forward, left; m/s), at the constraints' rate."""
        speed = math.hypot(vx_b, vy_b)
        if not speed >= MIN_SPEED_MPS:  # (NaN too)
            return
        c, s = (vx_b * vx_b - vy_b * vy_b) / speed**2, 2 * vx_b * vy_b / speed**2  # 2ψ
        axes = self._axes
        if len(axes) == axes.maxlen:
            old_c, old_s = axes[0]
            self._sum_c -= old_c
            self._sum_s -= old_s
        axes.append((c, s))
        self._sum_c += c
        self._sum_s += s
        self._judge()

    def clear(self) -> None:
        self._axes.clear()
        self._sum_c = self._sum_s = 0.0
        self.error_deg = None

    def _judge(self) -> None:
        n = len(self._axes)
        if n < MIN_SAMPLES:
            return
        c, s = self._sum_c / n, self._sum_s / n
        psi = math.degrees(math.atan2(s, c)) / 2
        self.error_deg = psi if math.hypot(c, s) >= MIN_AGREEMENT and abs(psi) > MAX_ERROR_DEG \
            else None

    def text(self) -> str:
        """One line a technician can act on ("": nothing found)."""
        if self.error_deg is None:
            return ""
        psi = self.error_deg
        return (f"the vehicle moves {abs(psi):.0f} deg to the body's "
                f"{'left' if psi > 0 else 'right'} of its forward axis (NHC on): imu.mounting "
                f"is likely turned about z by {psi:+.0f} deg; check imu.mounting")
