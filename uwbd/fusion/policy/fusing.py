"""One epoch's measurement update: its rows fused, each row's outcome reported.

The step of :class:`~uwbd.fusion.filter.Filter` after the policy has chosen the rows (the
ranges of an epoch, or a loose fix, with the ZUPT, NHC and height rows due): tight, on the
C core, the whole epoch in one call (:meth:`Eskf.fuse_ranges`); else the rows built
(:mod:`uwbd.fusion.models.measurements`) and fused one scalar at a time
(:meth:`Eskf.sequential_update`),
each range gated (χ²) and weighted (:class:`~uwbd.fusion.policy.robust.RowPolicy`), a loose fix
gated as one 3-D measurement; then every row's report, counters, health evidence and
anchor statistics, and the covariance kept within bounds. Its own state is the row
policies; it acts on the :class:`~.estimate.Estimate` and :class:`~.estimate.Findings` it is
handed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np

from uwbd.fusion.checks.anchor_consistency import CHECK_EVERY_NS
from uwbd.fusion.checks.gating import chi2_quantile
from uwbd.fusion.core.layout import BA_, BG_, P_, TH_
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.weights import RawRow, RowPolicy
from uwbd.fusion.models.measurements import (
    Rows,
    position_rows,
    range_check,
    range_keys,
    range_rows,
)
from uwbd.fusion.policy.estimate import Estimate, Findings
from uwbd.fusion.policy.installation import Installation
from uwbd.fusion.policy.robust import AnchorStats
from uwbd.fusion.settings import FilterConfig, Mode
from uwbd.fusion.types import FusionReport

ATTITUDE_AND_IMU_BIASES = slice(TH_.start, BA_.stop)
ATTITUDE_AND_GYRO_BIAS = slice(TH_.start, BG_.stop)
# the covariance is kept finite: no error state may be less certain than this (σ per state)
MAX_SIGMA = np.array([1e3] * 3 + [1e2] * 3 + [math.pi] * 3 + [0.5] * 3 + [5.0] * 3)
MAX_RANGE_BIAS_SIGMA_M = 5.0
MIN_KEPT_ANCHORS = 4  # an anchor is excluded only while this many others remain
EXCLUSION_RANGE_STATE_VAR_M2 = 0.1**2  # the others' range-model states widened by, then


class EpochFusion:
    """The update step (see module doc)."""

    def __init__(self, cfg: FilterConfig, est: Estimate, installation: Installation,
                 findings: Findings, imu_fresh: Callable[[], bool]) -> None:
        self.cfg, self.est, self.installation, self.findings = cfg, est, installation, findings
        self._imu_fresh = imu_fresh  # the IMU side's: the last IMU sample is recent
        self.at_rest = False  # ZUPT rows in this update
        self._policies: dict[tuple[str, bool], RowPolicy] = {}
        self._empty_rows: dict[int, Rows] = {}
        self._gate_1 = chi2_quantile(cfg.gate_probability, 1)
        self._gate_3 = chi2_quantile(cfg.gate_probability, 3)

    def apply_range_model(self, ids: list[int], anchors: Array, ranges: Array,
                          antenna: Array | None) -> Array:
        """The anchors' direction term at the prior position (it needs no attitude); the tag
        antenna's (:mod:`~uwbd.fusion.models.range_model`), once the heading is known: its
        degree 1 as the antenna's phase centre (the lever arm of the range rows), higher
        degrees taken off the ranges at the prior attitude. Before, the term would be turned
        by a heading that may be anything: only the phase centre's part along the vertical is
        applied (the tilt is known), the rest held back (the health note
        ``range_model_held``)."""
        model, ekf = self.cfg.range_model, self.est.ekf
        if antenna is not None and model.anchor_degree:
            ranges = ranges - model.anchor_term_m(ids, anchors, antenna)
        if not model.enabled:
            return ranges
        self.est.monitor.range_model_held = not self.est.aligned
        if ekf is None:
            return ranges
        plain, centre = self.installation.plain_lever, self.installation.model_lever
        if not self.est.aligned:
            w, x, y, z = ekf.q  # the vertical in body axes, Rᵀ e_z, whatever the heading:
            up_b = np.array((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))
            self.est.lever = plain + float((centre - plain) @ up_b) * up_b
            return ranges
        self.est.lever = centre
        if model.degree < 2:
            return ranges
        return ranges - model.higher_delay_m(ekf.q, ekf.p, centre.tolist(), anchors)

    def _measurement_rows(self, ids: list[int], anchors: Array, ranges: Array,
                          r_scale: Array, fix: LsqFix | None) -> Rows:
        """Tight: one row per range (§4, range); loose: the fix's axes (§4, position)."""
        ekf = self.est.ekf
        assert ekf is not None
        if self.cfg.mode is Mode.TIGHT:
            return range_rows(ekf, self.est.lever, ids, anchors, ranges,
                              self.cfg.range_sigma_m**2 * r_scale,
                              self.installation.range_columns, self.installation.lever_index)
        if fix is None:
            return Rows.empty(ekf.n)
        dims = 3 if self.installation.fixed_z is None else 2
        return position_rows(ekf, self.est.lever, fix, dims, self.cfg.range_sigma_m)

    def fuse_epoch(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                    r_scale: Array, fix: LsqFix | None,
                    constraints: list[Rows]) -> list[FusionReport]:
        """The epoch's rows fused: tight, on the C core, in one call (:meth:`Eskf.fuse_ranges`);
        else (loose, or the pure-Python reference) built here and fused by :meth:`_fuse`."""
        ekf = self.est.ekf
        assert ekf is not None
        if ids and self.cfg.mode is Mode.TIGHT and ekf.fuses_ranges:
            extra = Rows.stack(constraints) if constraints else self._no_rows(ekf.n)
            keys = range_keys(ids) + extra.keys
            outcome = ekf.fuse_ranges(
                self.est.lever, anchors, ranges, self.cfg.range_sigma_m**2 * r_scale,
                tuple(self.installation.range_columns.get(a, ()) for a in ids),
                self.installation.lever_index, extra[:3], self._row_policy(keys, True),
                self._considered(), ids)
            assert outcome is not None  # (fuses_ranges: the C core's, which always fuses)
            if None in outcome:  # ranges with no line to linearise: left out, unreported
                keys = [k for k, o in zip(keys, outcome, strict=True) if o is not None]
            return self._outcomes(t_ns, keys, [o for o in outcome if o is not None]
                                  if None in outcome else cast(list[RawRow], outcome))
        return self._fuse(t_ns, Rows.stack([self._measurement_rows(ids, anchors, ranges,
                                                                   r_scale, fix),
                                            *constraints]))

    def _fuse(self, t_ns: int, rows: Rows) -> list[FusionReport]:
        """Sequential scalar updates; each range gated (χ²) and weighted (robust); a loose
        fix gated as one 3-D measurement."""
        ekf = self.est.ekf
        assert ekf is not None
        H, y, R, keys = rows
        if not keys:
            return []
        fix_ok = True
        idx = np.array([k[0] == "position" for k in keys]) if self.cfg.mode is Mode.LOOSE \
            else None
        if idx is not None and idx.any():  # a position fix is one 3-D measurement: gate it as one
            Hl = H[idx]
            Sl = Hl @ ekf.P @ Hl.T + np.diag(R[idx])
            try:
                fix_ok = float(y[idx] @ np.linalg.solve(Sl, y[idx])) <= self._gate_3
            except np.linalg.LinAlgError:
                fix_ok = False
        anchor_of_row = [int(key) if kind == "range" else -1 for kind, key in keys]
        outcome = ekf.sequential_update(H, y, R, self._row_policy(keys, fix_ok),
                                        self._considered(), anchor_of_row)
        return self._outcomes(t_ns, keys, outcome)

    def check_anchors(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                       r_scale: Array) -> None:
        """The epoch's ranges, before the update, to the anchor test and the bias term's
        geometry: tight, with the heading known (the lever arm's direction). The snapshots'
        gain (:mod:`~uwbd.fusion.checks.bias_gain`: what a bias on every range can do),
        each range's variance its own plus the multipath state's; and the anchor test
        (:mod:`~uwbd.fusion.checks.anchor_consistency`: which one disagrees?), three
        ranges at least (a single range cannot be told from the others), about ten
        epochs a second (its σ takes them as that correlated)."""
        ekf, cfg = self.est.ekf, self.cfg
        if ekf is None or not ids or cfg.mode is not Mode.TIGHT or not self.est.aligned:
            return
        geometry, consistency = self.findings.geometry, self.findings.consistency
        snapshot = geometry.due(t_ns, ids)
        anchor_test = len(ids) >= 3 and t_ns - consistency.last_ns >= CHECK_EVERY_NS
        if not (snapshot or anchor_test):
            return
        var = cfg.range_sigma_m**2 * r_scale
        monitor = self.est.monitor
        # (the single-fault estimates only for the anchor test: single ranges come 100+ a
        # second)
        checked = range_check(ekf, self.est.lever, ids, anchors, ranges,
                              var if anchor_test else None, self.installation.range_columns)
        if checked is None:  # an antenna on an anchor: no line to test
            return
        U, _, b, d = checked
        if anchor_test:
            consistency.last_ns = t_ns
            if b is not None and d is not None:
                consistency.add_estimates(t_ns, ids, b, d)
            monitor.anchor_suspects = tuple(sorted(consistency.findings))
        if snapshot:  # (of the anchors in use)
            var = var + cfg.multipath_sigma_m**2 if cfg.multipath_states else var
            out = self.findings.excluded
            if out and any(a in out for a in ids):
                keep = np.array([a not in out for a in ids])
                ids, U, var = [a for a in ids if a not in out], U[keep], var[keep]
            geometry.add(t_ns, ids, U, var)
            monitor.bias_gain = geometry.bias_gain

    def exclude_findings(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                          r_scale: Array, reports: list[FusionReport]
                          ) -> tuple[list[int], Array, Array, Array]:
        """The ranges of the anchors the consistency test has found wrong (or the bank's
        separation, :mod:`.integrity`) are left out of the update (each reported,
        ``anchor_excluded``), as long as four other anchors remain; the test goes on judging
        them against the state, and they return once they agree."""
        out = self.decide_exclusions(ids)
        if not out:
            return ids, anchors, ranges, r_scale
        return self.leave_out(t_ns, out, ids, anchors, ranges, r_scale, reports)

    def decide_exclusions(self, ids: Sequence[int]) -> set[int]:
        """Which of ``ids`` are left out (found by the consistency test while enough others
        remain, or by the separation); those newly so leave the state (an adoption, or the
        state widened), and the health is told. Returns them."""
        findings = self.findings
        found, separated = findings.consistency.findings, findings.separated
        if len(self.installation.anchors) - len(found.keys() | separated.keys()) \
                < MIN_KEPT_ANCHORS:
            found = {}  # (the separation's are left out only while enough remain)
        # the anchors left out: those still found, and these ids' found ones
        out = {a for a in ids if a in found or a in separated}
        excluded = {a for a in findings.excluded if a in found or a in separated} | out
        adopted = False  # (one adoption a message: it starts the bank anew)
        for a in sorted(out - findings.excluded):
            adopted |= self._newly_excluded(a, found[a].bias_m if a in found else 0.0,
                                            adopt=not adopted)
        findings.excluded = excluded
        said = tuple(sorted(excluded))
        if said != self.est.monitor.excluded:  # (the health's view, refreshed on a change)
            self.est.monitor.excluded = said
            self.est.monitor.side_lost = self.installation.side_lost(excluded)
        return out

    def leave_out(self, t_ns: int, out: set[int], ids: list[int], anchors: Array,
                  ranges: Array, r_scale: Array, reports: list[FusionReport]
                  ) -> tuple[list[int], Array, Array, Array]:
        """The message without the ranges of the anchors ``out`` (each reported,
        ``anchor_excluded``)."""
        left = [FusionReport(t_ns, "range", str(a), math.nan, math.nan, math.nan, False,
                             "anchor_excluded") for a in ids if a in out]
        self.est.counters["range_excluded"] += len(left)
        reports += left
        keep = np.array([a not in out for a in ids])
        return ([a for a, k in zip(ids, keep, strict=True) if k], anchors[keep], ranges[keep],
                r_scale[keep])

    def _newly_excluded(self, anchor: int, bias_m: float, adopt: bool) -> bool:
        """The state has been pulled by this anchor's ranges: it becomes the bank's
        sub-filter that never took them (:meth:`~uwbd.fusion.core.eskf.Eskf.adopt`; with
        ``adopt`` — once a message: the bank starts anew); else its position and the other
        anchors' range-model states (which took part of the error) may move again. Whether
        it adopted."""
        ekf = self.est.ekf
        assert ekf is not None
        self.est.counters["anchors_excluded"] += 1
        if adopt and anchor in ekf.bank:
            ekf.adopt(ekf.bank.index(anchor))
            return True
        d = np.zeros(ekf.n)
        d[P_] = bias_m**2
        for other, columns in self.installation.range_columns.items():
            if other != anchor:
                d[list(columns)] += EXCLUSION_RANGE_STATE_VAR_M2
        ekf.add_variances(d)
        return False

    def range_policy(self) -> RowPolicy:
        """The policy of a single range's row (tracking: every state corrected)."""
        return self._row_policy([("range", "")], True)

    def _row_policy(self, keys: list[tuple[str, str]], fix_ok: bool) -> RowPolicy:
        # the first letter of each row's kind: "r"ange, "p"osition, any other gated plainly
        kinds = "".join([kind[0] for kind, _ in keys])
        policy = self._policies.get((kinds, fix_ok))
        if policy is None:  # a few shapes of update recur: each made once
            policy = self._policies[kinds, fix_ok] = self.cfg.robust.rows(
                kinds.encode(), self._gate_1, fix_ok)
        return policy

    def _no_rows(self, n: int) -> Rows:
        rows = self._empty_rows.get(n)
        if rows is None:
            rows = self._empty_rows[n] = Rows.empty(n)
        return rows

    def _considered(self) -> slice | None:
        """The states an update may not correct. While the heading is held, moving, its
        linearisation is void: attitude and gyro biases must not soak up what the unknown
        heading does to the velocity; without the IMU (coasting through a gap) nothing
        observes the attitude and the IMU's biases."""
        if not self._imu_fresh():
            return ATTITUDE_AND_IMU_BIASES
        if not self.est.aligned and not self.at_rest:
            return ATTITUDE_AND_GYRO_BIAS  # at rest the heading does not matter
        return None

    def _outcomes(self, t_ns: int, keys: list[tuple[str, str]],
                  outcome: Sequence[RawRow]) -> list[FusionReport]:
        """Each row's report, counters, health evidence and anchor statistics; then the
        covariance kept within bounds."""
        reports = self.row_outcomes(t_ns, keys, outcome)
        self._keep_covariance_sane()
        return reports

    def row_outcomes(self, t_ns: int, keys: list[tuple[str, str]],
                      outcome: Sequence[RawRow]) -> list[FusionReport]:
        gate_1 = self._gate_1
        reports = []
        counters, monitor = self.est.counters, self.est.monitor
        anchor_stats = self.findings.anchor_stats
        for (kind, key), (innovation, variance, weight, numerical) in zip(keys, outcome,
                                                                          strict=True):
            ok = weight > 0.0
            reason = "" if ok else ("numerical" if numerical else "innovation_gate")
            ratio = innovation**2 / variance / gate_1 if variance > 0 else math.nan
            reports.append(FusionReport(t_ns, kind, key, innovation, variance, ratio, ok,
                                        reason))
            counters[_OUTCOME_COUNTERS.get((kind, ok)) or _outcome_counter(kind, ok)] += 1
            if numerical:
                counters["numerical_skips"] += 1
                monitor.numerical_fault(t_ns)
            if kind in ("range", "position"):
                monitor.uwb_outcome(t_ns, ok, ratio * gate_1)
            if kind == "range":
                anchor = int(key)
                stats = anchor_stats.get(anchor)
                if stats is None:
                    stats = anchor_stats[anchor] = AnchorStats()
                stats.add(innovation / math.sqrt(variance) if variance > 0 else math.nan,
                          weight)
        return reports

    def _keep_covariance_sane(self) -> None:
        ekf = self.est.ekf
        assert ekf is not None
        if ekf.clamp_covariance(MAX_SIGMA, MAX_RANGE_BIAS_SIGMA_M):
            self.est.counters["covariance_clamped"] += 1


def _outcome_counter(kind: str, accepted: bool) -> str:
    """The fusion counter of a kind of row and its outcome ("range_accepted", …)."""
    return f"{kind}_{'accepted' if accepted else 'rejected'}"


_OUTCOME_COUNTERS = {(kind, ok): _outcome_counter(kind, ok)  # the known kinds', made once
                     for kind in ("range", "position", "zupt", "nhc", "height")
                     for ok in (True, False)}
