"""What the fusion core hands out: poses and per-measurement reports."""

from __future__ import annotations

from typing import NamedTuple

from uwbd.fusion.policy.health import WAITING, Health


class Pose(NamedTuple):
    """The body (IMU) pose in the ENU navigation frame at ``t_ns`` (Unix epoch ns).

    ``covariance`` is 6×6 row-major over (x, y, z, rotation about x, y, z), rotations in the
    navigation frame, as in ROS ``PoseWithCovariance``. (A named tuple, immutable: one is
    made for every pose, up to 200 a second, and a frozen dataclass took twice as long.)
    """

    t_ns: int
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    orientation_xyzw: tuple[float, float, float, float]
    covariance: tuple[float, ...]
    status: str  # the health record's one-line summary
    heading_observable: bool
    health: Health = WAITING


class FusionReport(NamedTuple):
    """One measurement's fate: innovation ``y``, its variance ``S``, ``nis = y²/S``, the
    test ratio (NIS over the gate; > 1 fails), accepted or the reason it was not.
    NaN fields mean the measurement never reached the innovation test (e.g. gated out by
    the range policy first). (A named tuple: every UWB measurement makes one, and a frozen
    dataclass took four times as long to make.)"""

    t_ns: int
    kind: str  # range | position | zupt | nhc | height
    key: str  # anchor id, or axis
    innovation: float
    innovation_var: float
    test_ratio: float
    accepted: bool
    reason: str = ""

    @property
    def nis(self) -> float:
        return self.innovation**2 / self.innovation_var
