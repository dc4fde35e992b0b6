"""What the fusion core hands out: poses and per-measurement reports."""

from __future__ import annotations

import math
from enum import Enum
from typing import Any, NamedTuple


class Phase(str, Enum):
    WAITING = "waiting"
    RECOVERING = "recovering"
    COASTING = "coasting"
    DEGRADED = "degraded"
    ALIGNING = "aligning"
    TRACKING = "tracking"


class Health(NamedTuple):
    """One step's verdict. Times are seconds; ``None`` where there is nothing to tell. A
    named tuple: immutable, and light enough for every pose to make one."""

    phase: Phase
    faults: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    since_range_s: float | None = None  # since the last accepted UWB measurement
    position_sigma_m: float | None = None  # horizontal, √(σx² + σy²)
    # the error bounds at the integrity risk (m; docs/ekf.md §6), None where not known
    horizontal_protection_m: float | None = None
    vertical_protection_m: float | None = None
    resets: int = 0
    last_reset_t_ns: int | None = None
    last_reset_reason: str = ""
    last_reset_jump_m: float | None = None  # how far the position moved at that reset
    # each protection level known and within its alert limit
    horizontal_available: bool = False
    vertical_available: bool = False

    @property
    def healthy(self) -> bool:
        return self.phase is Phase.TRACKING

    def summary(self) -> str:
        """One line for a terminal or ``systemctl status``."""
        if not self.faults and not self.notes and self.phase in _PLAIN:
            return _PLAIN[self.phase]  # (every pose has one: the common case at once)
        text = self.phase.value
        if self.phase is Phase.COASTING and self.since_range_s is not None:
            text += f" ({self.since_range_s:.1f} s without an accepted range)"
        if self.faults:
            text += ": " + ", ".join(self.faults)
        if self.phase is Phase.RECOVERING and self.last_reset_reason:
            text += f" (reset: {self.last_reset_reason})"
        if self.notes:
            text += "; " + ", ".join(self.notes)
        return text

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers as ``None``)."""
        num = _rounded  # (a module function: not made anew per call)
        return {"phase": self.phase.value, "healthy": self.healthy,
                "faults": list(self.faults), "notes": list(self.notes),
                "since_range_s": num(self.since_range_s),
                "position_sigma_m": num(self.position_sigma_m),
                "horizontal_protection_m": num(self.horizontal_protection_m),
                "vertical_protection_m": num(self.vertical_protection_m),
                "horizontal_available": self.horizontal_available,
                "vertical_available": self.vertical_available,
                "resets": self.resets,
                "last_reset_t_ns": self.last_reset_t_ns,
                "last_reset_reason": self.last_reset_reason,
                "last_reset_jump_m": num(self.last_reset_jump_m)}


def health_from_dict(d: dict[str, Any]) -> Health:
    """The record :meth:`Health.as_dict` wrote (a log's ``/pose``): what it holds, the rest
    at its default."""
    def num(key: str) -> float | None:
        v = d.get(key)
        return None if v is None else float(v)
    reset_t = d.get("last_reset_t_ns")
    return Health(Phase(d.get("phase", "waiting")), tuple(d.get("faults") or ()),
                  tuple(d.get("notes") or ()), num("since_range_s"), num("position_sigma_m"),
                  num("horizontal_protection_m"), num("vertical_protection_m"),
                  int(d.get("resets") or 0), None if reset_t is None else int(reset_t),
                  str(d.get("last_reset_reason") or ""), num("last_reset_jump_m"),
                  bool(d.get("horizontal_available")), bool(d.get("vertical_available")))


def _rounded(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, 4)


WAITING = Health(Phase.WAITING)
# the summaries of the phases whose line is their name alone when nothing is wrong
_PLAIN = {p: p.value for p in Phase if p not in (Phase.COASTING, Phase.RECOVERING)}



class Pose(NamedTuple):
    """The body (IMU) pose in the ENU navigation frame at ``t_ns`` (Unix epoch ns).

    ``covariance`` is 6×6 row-major over (x, y, z, rotation about x, y, z), rotations in the
    navigation frame, as in ROS ``PoseWithCovariance``. A named tuple: immutable, and light
    enough for every pose (up to 200 a second) to make one.
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
    the range policy first). A named tuple: light enough for every UWB measurement to make one."""

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
