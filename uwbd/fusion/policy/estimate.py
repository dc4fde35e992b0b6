"""The filter's state, declared once: what the parts of :class:`~uwbd.fusion.filter.Filter`
share, each concern a dataclass handed to the parts that read or change it.

* :class:`Estimate` — the core's numbers (``ekf``; ``None`` before a start and while
  restarting), their time, the heading (held, or aligned), the range rows' lever arm now,
  and the counters and health evidence every part adds to;
* :class:`Findings` — what the installation checks have found: the anchor test, the
  separation's suspect and the lever arm, the mounting, the anchors left out, each
  anchor's range statistics; and the ranges' geometry the bias term takes.

The parts keep their own state (the IMU side its last samples, the recovery its restart in
progress, the fusion its row policies); none reads another's but through these two.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

from uwbd.fusion.checks.anchor_consistency import AnchorConsistency, ConsistencyLimits
from uwbd.fusion.checks.bias_gain import BiasGain
from uwbd.fusion.checks.mounting_yaw import MountingYaw
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.alignment import HeadingAligner
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.policy.robust import AnchorStats
from uwbd.fusion.settings import FilterConfig


@dataclass(eq=False)
class Estimate:
    """The estimate and its evidence (see module doc)."""

    monitor: HealthMonitor
    aligner: HeadingAligner  # tells the heading while it is held (a new one at each restart)
    lever: Array  # the range rows' lever arm now: the antenna's, or its phase centre's
    keep_transition: bool  # keep each epoch's Φ (the smoother's, offline)
    ekf: Eskf | None = None
    t_ns: int | None = None  # the time of the nominal state
    aligned: bool = False  # the heading known (before: held, and the aligner at work)
    relevel: str | None = None  # an attitude restart pending: "keep" or "level" the tilt
    counters: collections.Counter[str] = field(default_factory=collections.Counter)


@dataclass(eq=False)
class Findings:
    """What the installation checks found (see module doc)."""

    geometry: BiasGain  # the ranges' geometry for the bias term (made with the filter's core)
    consistency: AnchorConsistency = field(
        default_factory=lambda: AnchorConsistency(ConsistencyLimits()))
    mounting_yaw: MountingYaw = field(default_factory=MountingYaw)
    mounting_finding: str = ""  # what the start at rest said of the mounting ("": nothing)
    excluded: set[int] = field(default_factory=set)  # the anchors left out of the last update
    # the anchors the bank's separation left out (policy.integrity): until when
    separated: dict[int, int] = field(default_factory=dict)
    anchor_stats: dict[int, AnchorStats] = field(default_factory=dict)
    # the separation test's finding while its alarm holds (policy.integrity): the anchor
    # it names and how far the sub-filter without it is from the filter (m); or the lever
    # arm, where its sub-filter puts the antenna (body, m)
    suspect: tuple[int, float] | None = None
    lever_arm_m: Array | None = None

    def forget(self) -> None:
        """At a restart: the evidence was against the old estimate."""
        self.consistency.clear()
        self.geometry.clear()
        self.separated.clear()
        self.excluded.clear()
        self.suspect = self.lever_arm_m = None
        self.mounting_yaw.clear()  # (the body velocity was the old heading's)


def new_aligner(cfg: FilterConfig) -> HeadingAligner:
    """A heading aligner with nothing seen yet (at the start, and at every restart)."""
    return HeadingAligner(cfg.align_window_s, cfg.align_min_dv_mps, cfg.range_sigma_m)
