"""The viewer channels: the transform tree, the anchors, the trajectories
(:mod:`uwbd.logs.foxglove`)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from typing import Any

from drivers.frames import Frame, UwbRanges
from uwbd.config import ConfigError, parse
from uwbd.fusion.policy.installation import MAX_ANCHOR_COORD_M
from uwbd.fusion.types import Pose
from uwbd.logs.foxglove.schemas import Vec3, stamp

TRAIL_SPACING_NS = 500_000_000  # a trajectory point every 0.5 s of data time
TRAIL_WINDOW_NS = 60_000_000_000  # the last minute
TRAIL_PERIOD_NS = 1_000_000_000  # sent once a second
ANCHOR_DIAMETER_M = 0.15
ANCHOR_COLOR = {"r": 1.0, "g": 0.55, "b": 0.0, "a": 1.0}
LABEL_COLOR = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}

def _point(position: Any) -> dict[str, float]:
    x, y, z = position
    return {"x": float(x), "y": float(y), "z": float(z)}


def _quat(q: Any) -> dict[str, float]:
    x, y, z, w = q
    return {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


class Trail:
    """A trajectory kept as points ``spacing_ns`` apart over the last ``window_ns``; every
    ``period_ns`` :meth:`add` hands out a ``foxglove.PosesInFrame`` of it."""

    def __init__(self, frame_id: str, spacing_ns: int = TRAIL_SPACING_NS,
                 window_ns: int = TRAIL_WINDOW_NS, period_ns: int = TRAIL_PERIOD_NS) -> None:
        self.frame_id = frame_id
        self.spacing_ns = spacing_ns
        self.window_ns = window_ns
        self.period_ns = period_ns
        self.points: deque[tuple[int, dict[str, Any]]] = deque()
        self._sent_ns: int | None = None

    def add(self, t_ns: int, position: Any, orientation_xyzw: Any) -> dict[str, Any] | None:
        points = self.points
        if not points or t_ns - points[-1][0] >= self.spacing_ns:
            if not all(map(math.isfinite, (*position, *orientation_xyzw))):
                return None  # a broken pose stays out of the drawing
            # 0.1 mm and 1e-4 are far below what a viewer shows, and halve the record
            x, y, z = (round(float(v), 4) for v in position)
            qx, qy, qz, qw = (round(float(v), 4) for v in orientation_xyzw)
            points.append((t_ns, {"position": {"x": x, "y": y, "z": z},
                                  "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}))
            while t_ns - points[0][0] > self.window_ns:
                points.popleft()
        if self._sent_ns is not None and t_ns - self._sent_ns < self.period_ns:
            return None
        self._sent_ns = t_ns
        return {"timestamp": stamp(t_ns), "frame_id": self.frame_id,
                "poses": [p for _, p in points]}


class FoxgloveView:
    """The state behind the viewer channels of one run: frame names, the anchors (configured,
    and those the device reports, taken as the filter takes them), the trajectories.

    Shared by the files of a rotating log (the trajectory goes on across files) and used on
    its own by the live server."""

    def __init__(self, nav_frame_id: str = "enu", body_frame_id: str = "base_link",
                 anchors_m: Mapping[int, Vec3] | None = None) -> None:
        self.nav_frame_id = nav_frame_id
        self.body_frame_id = body_frame_id
        self.anchors_m: dict[int, Vec3] = dict(anchors_m or {})
        self.anchors_version = 1 if self.anchors_m else 0  # +1 at each change
        self.trail = Trail(nav_frame_id)
        self.truth_trail = Trail(nav_frame_id)

    @classmethod
    def from_config(cls, config: Any) -> FoxgloveView:
        """From a :class:`uwbd.config.Config`."""
        return cls(config.nav_frame_id, config.body_frame_id, config.anchors_m)

    @classmethod
    def from_toml(cls, text: str) -> FoxgloveView:
        """From a config's TOML (a log's metadata); the defaults if it does not parse."""
        try:
            return cls.from_config(parse(text, "log config"))
        except ConfigError:
            return cls()

    def observe(self, frame: Frame) -> bool:
        """Anchors the device reports with its ranges (configured positions win, as in the
        filter); True when the set changed."""
        if not isinstance(frame, UwbRanges):
            return False
        changed = False
        for r in frame.ranges:
            pos = r.anchor_position_m
            if (pos is not None and r.anchor_id not in self.anchors_m
                    and max(map(abs, pos)) <= MAX_ANCHOR_COORD_M):  # NaN fails too
                self.anchors_m[r.anchor_id] = (float(pos[0]), float(pos[1]), float(pos[2]))
                changed = True
        if changed:
            self.anchors_version += 1
        return changed

    def transform(self, pose: Pose) -> dict[str, Any]:
        """``/tf``: the body frame in the navigation frame."""
        return {"timestamp": stamp(pose.t_ns), "parent_frame_id": self.nav_frame_id,
                "child_frame_id": self.body_frame_id,
                "translation": _point(pose.position_m),
                "rotation": _quat(pose.orientation_xyzw)}

    def scene(self, t_ns: int) -> dict[str, Any]:
        """``/anchors``: a sphere and an id label per anchor."""
        identity = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
        size = {"x": ANCHOR_DIAMETER_M, "y": ANCHOR_DIAMETER_M, "z": ANCHOR_DIAMETER_M}
        entities = []
        for anchor_id, pos in sorted(self.anchors_m.items()):
            label = dict(_point(pos))
            label["z"] += ANCHOR_DIAMETER_M
            entities.append({
                "timestamp": stamp(t_ns), "frame_id": self.nav_frame_id,
                "id": f"anchor-{anchor_id}", "lifetime": {"sec": 0, "nsec": 0},
                "frame_locked": False,
                "metadata": [{"key": "anchor_id", "value": str(anchor_id)}],
                "arrows": [], "cubes": [],
                "spheres": [{"pose": {"position": _point(pos), "orientation": identity},
                             "size": size, "color": ANCHOR_COLOR}],
                "cylinders": [], "lines": [], "triangles": [],
                "texts": [{"pose": {"position": label, "orientation": identity},
                           "billboard": True, "font_size": 14.0, "scale_invariant": True,
                           "color": LABEL_COLOR, "text": f"anchor {anchor_id}"}],
                "models": []})
        return {"deletions": [], "entities": entities}

    def trajectory(self, pose: Pose) -> dict[str, Any] | None:
        """``/trajectory`` when one is due."""
        return self.trail.add(pose.t_ns, pose.position_m, pose.orientation_xyzw)

    def truth_trajectory(self, t_ns: int, truth: Mapping[str, Any]) -> dict[str, Any] | None:
        """``/truth/trajectory`` when one is due, from a ``/truth`` record."""
        try:
            p, q = truth["pose"]["position"], truth["pose"]["orientation"]
            position = (p["x"], p["y"], p["z"])
            orientation = (q["x"], q["y"], q["z"], q["w"])
        except (KeyError, TypeError):
            return None
        return self.truth_trail.add(t_ns, position, orientation)
