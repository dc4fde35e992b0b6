"""Poses against a simulation's truth: the helper the fusion tests share."""

from __future__ import annotations

import numpy as np

from uwbd.fusion.types import Pose
from uwbd.tools.simulator import Simulation


def position_errors(poses: list[Pose], sim: Simulation) -> np.ndarray:
    """Each pose's position minus the truth at its time (n × 3, m, ENU)."""
    t = np.array([p.t_ns for p in poses])
    truth = np.column_stack([np.interp(t, sim.truth_t_ns, sim.truth_p_m[:, i])
                             for i in range(3)])
    return np.array([p.position_m for p in poses]).reshape(-1, 3) - truth
