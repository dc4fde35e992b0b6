"""The anchors the filter knows and what follows from them: the mirror side of a plane of
them, the height held over coplanar ones, the state's columns for each anchor's range-model
states and the lever arm's, and each message's ranges resolved to anchor positions."""

from __future__ import annotations

import math

import numpy as np

from drivers.frames import UwbRanges
from uwbd.fusion.checks.gating import GatingCounters
from uwbd.fusion.checks.separation import LEVER_MEMBER
from uwbd.fusion.core.layout import N_CORE
from uwbd.fusion.core.lsq import coplanar
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.fixes import RangeWindow
from uwbd.fusion.policy.mirror import WALL_NORMAL_Z, MirrorSide
from uwbd.fusion.policy.robust import quality_scale
from uwbd.fusion.settings import FilterConfig, Mode
from uwbd.fusion.types import FusionReport

Vec3 = tuple[float, float, float]
MAX_ANCHOR_COORD_M = 1e4  # a device-reported anchor farther out than this is garbage
Resolved = tuple[list[int], Array, Array, Array]  # anchor ids, positions, ranges, r scales
LEVER_TEST_SIGMA_M = 0.3  # the bank's lever member's prior σ on each axis of its error


class Installation:
    """The anchors (configured, and those the device reports) and the state layout they
    give; laid out again before a start when the device has reported a new one."""

    def __init__(self, cfg: FilterConfig, ranges: RangeWindow, core: Core) -> None:
        self.cfg = cfg
        self._core = core  # the mirror side's least squares: C, or the reference (None)
        self.ranges = ranges  # told the mirror side and the held height
        self.anchors: dict[int, Vec3] = dict(cfg.anchors_m)
        # the configured anchors whose every coordinate is finite and in range (resolve)
        self.configured = {a: pos for a, pos in cfg.anchors_m.items()
                           if all(abs(c) <= MAX_ANCHOR_COORD_M for c in pos)}
        # their positions and variance factors as arrays, by the epoch's anchor ids
        self._arrays: dict[tuple[int, ...], tuple[Array, Array]] = {}
        # range rows' lever arm: the antenna's, or, with the range model applied, its phase
        # centre's (EpochFusion.apply_range_model)
        self.plain_lever = np.array(cfg.lever_arm_m, dtype=float)
        self.model_lever = self.plain_lever + cfg.range_model.phase_centre_m()
        self.mirror = ranges.side
        self.fixed_z: float | None = None
        self.bias_index: dict[int, int] = {}
        self.mp_index: dict[int, int] = {}
        self.range_columns: dict[int, tuple[int, ...]] = {}
        self.lever_index: tuple[int, ...] = ()  # the lever arm's error states (tight)
        # whether the main filter estimates them (else it holds them at 0, known)
        self.lever_estimated = cfg.lever_arm_sigma_m > 0 and cfg.mode is Mode.TIGHT
        self.bank: tuple[int, ...] = ()  # the anchors the bank's sub-filters leave out
        self._side_lost: dict[frozenset[int], bool] = {}  # side_lost's answers
        self.new_anchors = False  # reported since the last start: laid out before the next
        self.lay_out()

    def lay_out(self) -> None:
        """What follows from the anchors: the mirror side of a plane of them, the height
        held over coplanar ones, and one antenna-delay and one multipath state each."""
        cfg = self.cfg
        anchors = np.array(list(self.anchors.values()), dtype=float).reshape(-1, 3)
        bias_sigma_m = math.hypot(cfg.range_bias_sigma_m, cfg.tag_delay_sigma_m,
                                  cfg.multipath_sigma_m if cfg.multipath_states else 0.0)
        old, self.mirror = self.mirror, MirrorSide(anchors, cfg.tag_side, cfg.height_range_m,
                                                   bias_sigma_m=bias_sigma_m, core=self._core)
        if old.decided_by.startswith("ranges") and self.mirror.ambiguous:
            # what the ranges told about the side still holds with one anchor more
            self.mirror.sign, self.mirror.resolved = old.sign, old.resolved
            self.mirror.decided_by = old.decided_by
        # a known height replaces the vertical that a (horizontal) plane of anchors cannot
        # tell; over a wall the height is observed and the mirror is sideways
        horizontal = abs(float(self.mirror.normal[2])) >= WALL_NORMAL_Z
        self.fixed_z = (cfg.known_height_m
                        if len(anchors) and coplanar(anchors) and horizontal else None)
        self.ranges.side, self.ranges.fixed_z = self.mirror, self.fixed_z
        self._side_lost.clear()
        ids = sorted(self.anchors)
        tight = cfg.mode is Mode.TIGHT  # the offsets are unobservable from loose fixes
        self.bias_index = ({a: N_CORE + i for i, a in enumerate(ids)}
                           if cfg.range_bias_states and tight else {})
        first = N_CORE + len(self.bias_index)
        self.mp_index = ({a: first + i for i, a in enumerate(ids)}
                         if cfg.multipath_states and tight else {})
        # the lever arm's error, three constant states after those: estimated by the main
        # filter with [fusion] lever_arm_sigma_m, else by the bank's lever member alone
        last = first + len(self.mp_index)
        self.lever_index = (last, last + 1, last + 2) if tight else ()
        # the bank's sub-filters, one leaving each anchor out (integrity), and the lever
        # member: tight only, where each range is a row of its own
        self.bank = (tuple(ids) + (() if self.lever_estimated else (LEVER_MEMBER,))
                     if tight else ())
        # each anchor's range-model state columns, for its range rows
        self.range_columns = {a: tuple(c for index in (self.bias_index, self.mp_index)
                                       if (c := index.get(a)) is not None) for a in ids}

    def bank_variances(self) -> Array:
        """What each of the bank's sub-filters adds to the main filter's variances at every
        start anew (K × n): the lever member its prior on the lever arm's error."""
        n = N_CORE + len(self.bias_index) + len(self.mp_index) + len(self.lever_index)
        out = np.zeros((len(self.bank), n))
        if LEVER_MEMBER in self.bank:
            out[self.bank.index(LEVER_MEMBER), list(self.lever_index)] = LEVER_TEST_SIGMA_M**2
        return out

    def side_lost(self, excluded: set[int]) -> bool:
        """Whether leaving ``excluded`` out loses the side of the anchors' plane: the whole
        layout told it (it has no mirror, or the ranges decided it), the anchors left form a
        horizontal plane (which has one), and no hint says it. The height is then not known
        (the health says so)."""
        told = not self.mirror.ambiguous or self.mirror.decided_by.startswith("ranges")
        if not excluded or not told or self.cfg.tag_side != "auto" \
                or self.cfg.height_range_m is not None:
            return False
        key = frozenset(excluded)
        lost = self._side_lost.get(key)
        if lost is None:
            rest = np.array([p for a, p in self.anchors.items() if a not in excluded],
                            dtype=float).reshape(-1, 3)
            lost = self._side_lost[key] = len(rest) >= 3 and coplanar(rest) and \
                abs(float(MirrorSide(rest, core=self._core).normal[2])) >= WALL_NORMAL_Z
        return lost

    def resolve(self, epoch: UwbRanges, gating: GatingCounters,
                reports: list[FusionReport]) -> Resolved:
        """Anchor positions for each range (configured first, else as the device sends: a
        new one is added to :attr:`anchors`), the ranges less the range model's
        attitude-free part, and the factor on each range's variance from the device's
        quality."""
        ids, anchors, ranges, scale = [], [], [], []
        configured = self.configured
        common = True  # every range to a configured anchor, with no quality
        for r in epoch.ranges:
            pos = configured.get(r.anchor_id)
            if pos is not None and r.quality is None:  # the common case: checked once
                ids.append(r.anchor_id)
                anchors.append(pos)
                ranges.append(r.range_m)
                scale.append(1.0)
                continue
            common = False
            pos = self.cfg.anchors_m.get(r.anchor_id, r.anchor_position_m)
            # every coordinate finite and in range (max() would let a NaN after the first by)
            if pos is None or not all(abs(c) <= MAX_ANCHOR_COORD_M for c in pos):
                why = "unknown_anchor" if pos is None else "anchor_position_invalid"
                gating.rejections[why] += 1
                reports.append(FusionReport(epoch.t_ns, "range", str(r.anchor_id), math.nan,
                                            math.nan, math.nan, False, why))
                continue
            self.anchors.setdefault(r.anchor_id, pos)  # reported by the device
            ids.append(r.anchor_id)
            anchors.append(pos)
            ranges.append(r.range_m)
            scale.append(quality_scale(r.quality))
        if self.cfg.range_model.corrects_ranges:  # the anchors' calibrated delays, distance
            ranges = self.cfg.range_model.corrected_m(ids, ranges)
        if common:  # the same anchors recur: their arrays made once (read only downstream)
            key = tuple(ids)
            arrays = self._arrays.get(key)
            if arrays is None:
                arrays = self._arrays[key] = (np.array(anchors, dtype=float).reshape(-1, 3),
                                              np.ones(len(ids)))
                for a in arrays:
                    a.flags.writeable = False
            return ids, arrays[0], np.array(ranges), arrays[1]
        return (ids, np.array(anchors, dtype=float).reshape(-1, 3), np.array(ranges),
                np.array(scale))
