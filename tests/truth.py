"""Poses against a simulation's truth, and the alert limits of tests about the estimate
rather than its protection levels: the helpers the fusion tests share."""

from __future__ import annotations

import numpy as np

from uwbd.fusion.settings import HealthLimits
from uwbd.fusion.types import Pose
from uwbd.tools.simulator import Simulation

# The simulator's default layout (six anchors, two of them high, 0.1 m ranges) cannot hold
# the default alert limits (0.5 m, 1.0 m) over each anchor's fault (the campaign measures
# where they hold): tests that judge the estimate, not its levels, widen them.
WIDE_LIMITS = HealthLimits(horizontal_alert_limit_m=2.0, vertical_alert_limit_m=3.0)


def wide_limits_toml(text: str) -> str:
    """A config's text (``uwbd simulate``'s) with :data:`WIDE_LIMITS` in its [fusion]."""
    return text.replace("[fusion]\n", "[fusion]\nhorizontal_alert_limit_m = 2.0\n"
                        "vertical_alert_limit_m = 3.0\n", 1)


def position_errors(poses: list[Pose], sim: Simulation) -> np.ndarray:
    """Each pose's position minus the truth at its time (n × 3, m, ENU)."""
    t = np.array([p.t_ns for p in poses])
    truth = np.column_stack([np.interp(t, sim.truth_t_ns, sim.truth_p_m[:, i])
                             for i in range(3)])
    return np.array([p.position_m for p in poses]).reshape(-1, 3) - truth
