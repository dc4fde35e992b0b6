"""The daemon's running commentary: a sink that turns poses and status into log lines.

It says when the first pose leaves, every change of the filter's phase (``waiting`` →
``aligning`` → ``tracking``, ``coasting``, ``degraded``, ``recovering``), when every range so
far has been rejected and why, and every ``summary_s`` one line of health: poses a second,
ranges accepted and rejected since the last line, the horizontal σ, the ports. It never
raises into the pipeline and costs one comparison per pose.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from drivers import Frame
from uwbd import journal
from uwbd.fusion.types import Pose

LOG = journal.get("daemon")
ALL_REJECTED_AFTER_NS = 5_000_000_000  # ranges arriving this long, none accepted: say why


class Narrator:
    def __init__(self, summary_s: float = 60.0,
                 ports: Callable[[], str] = lambda: "") -> None:
        self.summary_ns = int(summary_s * 1e9)
        self.ports = ports  # the ports' states, one short text
        self._phase = ""
        self._first_pose = True
        self._last_summary: tuple[int, int, int, int] | None = None  # t, poses, ok, rejected
        self._first_range_ns: int | None = None
        self._said_all_rejected = False
        self._sink_errors: set[str] = set()
        self._findings_said: set[Any] = set()  # the anchors of the findings said
        self._mounting_said = ""

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        """Bytes are not narrated."""

    def frame(self, frame: Frame) -> None:
        """Frames are not narrated."""

    def pose(self, pose: Pose) -> None:
        if self._first_pose:
            self._first_pose = False
            x, y, z = pose.position_m
            LOG.info("first pose: (%.2f, %.2f, %.2f) m, %s", x, y, z, pose.health.summary())
        phase = pose.health.phase.value
        if phase != self._phase:
            self._phase_changed(phase, pose.health.summary())

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        health = status.get("health", {})
        phase = str(health.get("phase", ""))
        if phase and phase != self._phase:
            self._phase_changed(phase, str(status.get("filter", phase)))
        findings: dict[Any, str] = {
            f.get("anchor"): str(f.get("finding", f"anchor {f.get('anchor')} disagrees"))
            for f in status.get("anchor_findings", [])}
        suspected = status.get("anchor_suspected")
        if suspected:  # the separation's, among too few to leave it out
            findings["separation", suspected.get("anchor")] = str(suspected.get("finding"))
        lever = status.get("lever_arm_finding")
        if lever:
            findings["lever"] = str(lever.get("finding", "the lever arm looks off"))
        for key in findings.keys() - self._findings_said:  # said again only once it agreed
            LOG.warning("%s", findings[key])
        self._findings_said = set(findings)
        mounting = str(status.get("mounting_finding", ""))
        if mounting and mounting != self._mounting_said:
            LOG.warning("%s", mounting)
        self._mounting_said = mounting
        counters = status.get("fusion_counters", {})
        accepted = int(counters.get("range_accepted", 0))
        rejected = int(counters.get("range_rejected", 0)) + sum(  # ranges, not epochs
            n for reason, n in status.get("gating_rejections", {}).items()
            if reason != "too_few_anchors")
        self._all_rejected(t_ns, accepted, rejected, status)
        for error in status.get("sink_errors", []):
            # the pipeline and the log sink say their errors as they happen; here a sink's
            # error is said again only if it is a new one ("X failed 3x, last: ..." counts up)
            said = error.split(" failed ")[0] + error.partition(", last: ")[2]
            if said not in self._sink_errors:
                self._sink_errors.add(said)
        poses = int(status.get("poses", 0))
        last = self._last_summary
        if last is None:
            self._last_summary = (t_ns, poses, accepted, rejected)
        elif t_ns - last[0] >= self.summary_ns:
            self._last_summary = (t_ns, poses, accepted, rejected)
            rate = (poses - last[1]) / ((t_ns - last[0]) / 1e9)
            sigma = health.get("position_sigma_m")
            hpl, vpl = health.get("horizontal_protection_m"), health.get("vertical_protection_m")
            LOG.info("%s; %.1f poses/s; ranges %d accepted, %d rejected in %.0f s; σxy %s; "
                     "protection %s%s", status.get("filter", phase), rate, accepted - last[2],
                     rejected - last[3], (t_ns - last[0]) / 1e9,
                     "-" if sigma is None else f"{sigma:.3f} m",
                     "-" if hpl is None or vpl is None else f"{hpl:.2f} m h, {vpl:.2f} m v",
                     f"; {self.ports()}" if self.ports() else "")

    def _phase_changed(self, phase: str, text: str) -> None:
        was, self._phase = self._phase, phase
        if was:
            log = LOG.info if phase in ("tracking", "aligning") else LOG.warning
            log("filter %s -> %s", was, text)

    def _all_rejected(self, t_ns: int, accepted: int, rejected: int,
                      status: dict[str, Any]) -> None:
        if self._said_all_rejected or not rejected:
            return
        if accepted:
            self._said_all_rejected = True  # ranges work: nothing to say
            return
        if self._first_range_ns is None:
            self._first_range_ns = t_ns
        elif t_ns - self._first_range_ns >= ALL_REJECTED_AFTER_NS:
            self._said_all_rejected = True
            reasons = dict(status.get("gating_rejections", {}))
            reasons.update({k: v for k, v in status.get("fusion_counters", {}).items()
                            if k == "range_rejected"})
            hint = (" — is [anchors] in the config? this tag does not send anchor positions"
                    if "unknown_anchor" in reasons else "")
            LOG.warning("every range rejected so far (%d): %s%s", rejected,
                        ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())), hint)

    def close(self) -> None:
        """Nothing to release."""
