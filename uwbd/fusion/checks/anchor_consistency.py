"""Which anchor disagrees with the others: each epoch's ranges tested one by one against the
prediction, over a window (fault detection, in the spirit of GNSS RAIM).

An epoch's innovations ``ν`` (measured minus predicted ranges, before the update) have the
covariance ``S = H P Hᵀ + R``. If range ``j`` alone carried an error ``b``, the best estimate
of it is Baarda's (data snooping) ``b̂_j = (S⁻¹ν)_j / (S⁻¹)_jj`` with variance ``1/(S⁻¹)_jj``:
unlike the raw innovation it does not blame the correct neighbours of a wrong anchor, whose
innovations the filter's compromise between them has made large. One epoch's ``b̂`` is
noise; a wrong installation (an anchor surveyed off, a biased anchor) makes it persistent,
so it is averaged per anchor over ``window_s``. Successive epochs share the state's error,
so the average's σ is taken as if only one epoch in ``CORRELATED_EPOCHS`` were independent.

An anchor is a *suspect* when its average is larger than ``alarm_m`` and than ``z`` times
its σ, and is the largest such of the epoch's anchors (one fault at a time: the others'
averages are partly its image). A suspect tested so for ``persist_s`` (no gap over
``gap_s``) is a finding: an NLOS burst makes one anchor's ranges long for seconds, a wrong
survey for good. It stands until ``hold_s`` without such a test (and, while the test has
too few epochs of its anchor to judge it, until it has).
Whether its position or its range offset is wrong is not told: the filter's state has
moved to meet the anchor part of the way (and its range-model state has taken some of an
offset), so what is left of the error does not follow the direction to the tag closely
enough to tell them apart (measured on the simulator). Found by it on the simulator's
layout: an anchor 1 m off sideways; not found: 1 m off in height (the error goes into the
tag's height, which the ranges hardly see), mostly not: a +0.5 m offset (the range-model
state takes most of it). The filter leaves a found anchor's ranges out
(:mod:`uwbd.fusion.policy.fusing`); this test goes on judging them.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from uwbd.fusion.core.rotation import Array

NS = 1_000_000_000
CHECK_EVERY_NS = 95_000_000  # epochs taken about ten a second, whatever the device's rate
CORRELATED_EPOCHS = 10  # and those share their error over about a second
MIN_ENTRIES = 30  # an anchor's average judged only from this many epochs on


@dataclass(frozen=True)
class ConsistencyLimits:
    window_s: float = 8.0
    alarm_m: float = 0.25  # an average this large is worth a technician's look
    z: float = 4.0
    persist_s: float = 8.0  # a suspect this long (no gap over gap_s) is a finding: an NLOS
    gap_s: float = 2.0  # burst makes an anchor's ranges long for seconds, a wrong survey for good
    hold_s: float = 10.0  # a finding stands this long after its anchor last tested so


@dataclass(frozen=True)
class Finding:
    """A suspect anchor: its ranges' average error against the others', and its σ."""

    anchor: int
    bias_m: float
    sigma_m: float

    def text(self) -> str:
        """One line a technician can act on."""
        long = "long" if self.bias_m > 0 else "short"
        return (f"anchor {self.anchor}: its ranges are ~{abs(self.bias_m):.2f} m {long} "
                f"against the other anchors': its surveyed position or its range offset is "
                f"likely wrong (check the survey, uwbd survey, and the anchor)")

    def as_dict(self) -> dict[str, object]:
        return {"anchor": self.anchor, "bias_m": round(self.bias_m, 3),
                "sigma_m": round(self.sigma_m, 3), "finding": self.text()}


class AnchorConsistency:
    """The per-anchor windows of ``b̂`` and the suspects (see module doc)."""

    def __init__(self, limits: ConsistencyLimits) -> None:
        self.limits = limits
        self._windows: dict[int, _Window] = {}
        self.findings: dict[int, Finding] = {}
        self._found_ns: dict[int, int] = {}  # when each finding last tested positive
        self._suspect: dict[int, tuple[int, int]] = {}  # first and last positive test
        self.last_ns = -(2**63)  # the last epoch taken (the caller's rate)

    def add(self, t_ns: int, ids: list[int], nu: Array, S: Array) -> None:
        """One epoch: its anchors, their innovations and the innovations' covariance."""
        estimates = single_fault_estimates(nu, S)
        if estimates is not None:
            self.add_estimates(t_ns, ids, *estimates)

    def add_estimates(self, t_ns: int, ids: list[int], b: Array, d: Array) -> None:
        """One epoch as :func:`single_fault_estimates` gives it (or the C core's
        ``State.range_check``): each range's ``b̂`` and its weight ``(S⁻¹)_jj``."""
        for anchor, bk, dk in zip(ids, b.tolist(), d.tolist(), strict=True):
            if dk > 0 and math.isfinite(bk):
                window = self._windows.get(anchor)
                if window is None:
                    window = self._windows[anchor] = _Window()
                window.add(t_ns, bk, dk)  # b̂ and its weight 1/var = (S⁻¹)_jj
        self._judge(t_ns)

    def found(self, t_ns: int, anchor: int, bias_m: float, sigma_m: float) -> None:
        """A finding made elsewhere (a start at rest that left the anchor out): it stands
        until this test has judged the anchor (``MIN_ENTRIES`` epochs), then as the test's
        own do, ``hold_s`` unless the test confirms it."""
        self.findings[anchor] = Finding(anchor, bias_m, sigma_m)
        self._found_ns[anchor] = t_ns

    def clear(self) -> None:
        """A restart: the evidence was about the old estimate."""
        self._windows.clear()
        self.findings.clear()
        self._found_ns.clear()
        self._suspect.clear()

    def _judge(self, t_ns: int) -> None:
        lim = self.limits
        oldest = t_ns - lim.window_s * NS
        best: tuple[float, int, float, float] | None = None
        for anchor, window in self._windows.items():
            window.forget_before(oldest)
            if len(window.entries) < MIN_ENTRIES or not window.sum_w > 0:
                continue
            mean = window.sum_wb / window.sum_w
            sigma = math.sqrt(CORRELATED_EPOCHS / window.sum_w)
            score = abs(mean) / sigma
            if best is None or score > best[0]:
                best = (score, anchor, mean, sigma)
        for anchor, (_, last_ns) in list(self._suspect.items()):
            if t_ns - last_ns > lim.gap_s * NS:
                del self._suspect[anchor]  # the run of positive tests broke off
        if best is not None and best[0] > lim.z and abs(best[2]) > lim.alarm_m:
            _, anchor, mean, sigma = best
            since_ns = self._suspect.get(anchor, (t_ns, t_ns))[0]
            self._suspect[anchor] = (since_ns, t_ns)
            if t_ns - since_ns >= lim.persist_s * NS or anchor in self.findings:
                self.findings[anchor] = Finding(anchor, mean, sigma)
                self._found_ns[anchor] = t_ns
        for anchor, found_ns in list(self._found_ns.items()):  # held, then gone
            judged = self._windows.get(anchor)
            if judged is None or len(judged.entries) < MIN_ENTRIES:
                self._found_ns[anchor] = t_ns  # not judged here yet: it stands until it is
            elif t_ns - found_ns > lim.hold_s * NS:
                del self._found_ns[anchor], self.findings[anchor]


def single_fault_estimates(nu: Array, S: Array) -> tuple[Array, Array] | None:
    """Baarda's single-fault estimate of each innovation, ``b̂_j = (S⁻¹ν)_j / (S⁻¹)_jj``,
    and its weight ``(S⁻¹)_jj``; None when ``S`` is singular. (The reference of the C
    core's, in ``State.range_check``.)"""
    try:
        Si = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    d = np.diag(Si)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (Si @ nu) / d, d


class _Window:
    """One anchor's ``(t_ns, b̂, weight)`` over the window and their weighted sums (kept as
    entries come and go: at 50 Hz epochs a window holds hundreds)."""

    def __init__(self) -> None:
        self.entries: collections.deque[tuple[int, float, float]] = collections.deque()
        self.sum_w = self.sum_wb = 0.0

    def add(self, t_ns: int, b: float, w: float) -> None:
        self.entries.append((t_ns, b, w))
        self.sum_w += w
        self.sum_wb += w * b

    def forget_before(self, oldest_ns: float) -> None:
        entries = self.entries
        while entries and entries[0][0] < oldest_ns:
            _, b, w = entries.popleft()
            self.sum_w -= w
            self.sum_wb -= w * b
        if not entries:  # (and no rounding left behind)
            self.sum_w = self.sum_wb = 0.0
