"""Running a survey: the log's ranges read, the anchor-to-anchor layout and the tag's batch
adjustment (:mod:`uwbd.tools.survey` says how) combined into one :class:`Survey`."""


from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from drivers import PARSERS
from drivers.frames import AnchorRanges, Frame, UwbRanges
from uwbd.codec import frame_from_dict
from uwbd.fusion.core.lsq import coplanar
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.models.range_model import RangeModel
from uwbd.logs.reading import LogContents
from uwbd.tools.survey.adjustment import (
    Confined,
    Problem,
    anchor_covariance,
    layout_part,
    solve,
    tag_data,
    trusted_directions,
    usable,
)
from uwbd.tools.survey.model import (
    COPLANAR_M,
    MAD_TO_SIGMA,
    MIN_EPOCH_RANGES,
    AnchorEstimate,
    Settings,
    Survey,
    SurveyError,
    Vec3,
    frame_of,
    side_of,
)
from uwbd.tools.survey.pairs import pairs_start, reached_by, reduce_pairs


def log_ranges(contents: LogContents) -> tuple[list[UwbRanges], list[AnchorRanges]]:
    """The tag ranges and anchor-to-anchor ranges a log holds: its raw channels through the
    drivers its metadata names, else its decoded ``/uwb`` and ``/anchor_ranges`` records
    (a live log has both: the raw bytes are the record, the decoded ones a copy)."""
    sources = json.loads(contents.metadata.get("sources", "[]") or "[]")
    raw = {f"/raw/{s['name']}": s["driver"] for s in sources if s.get("driver") in PARSERS}
    uwb: list[UwbRanges] = []
    pairs: list[AnchorRanges] = []

    def take(frames: Iterable[Frame]) -> None:
        for f in frames:
            if isinstance(f, UwbRanges):
                uwb.append(f)
            elif isinstance(f, AnchorRanges):
                pairs.append(f)

    if any(m.topic in raw for m in contents.messages):
        parsers = {topic: PARSERS[driver]() for topic, driver in raw.items()}
        for m in contents.messages:
            parser = parsers.get(m.topic)
            if parser is not None:
                take(parser.feed(m.data, m.log_time_ns))
        for parser in parsers.values():
            take(parser.flush())
    else:
        for m in contents.messages:
            if m.topic in ("/uwb", "/anchor_ranges"):
                try:
                    take([frame_from_dict(json.loads(m.data))])
                except (ValueError, KeyError, TypeError, IndexError):
                    continue  # a damaged record: the others go on
    uwb.sort(key=lambda f: f.t_ns)
    pairs.sort(key=lambda f: f.t_ns)
    return uwb, pairs


def _check_ids(settings: Settings, known: set[int]) -> None:
    g = settings.gauge
    ids = ", ".join(str(a) for a in sorted(known)) or "none"
    for name, value in (("--origin", g.origin), ("--x-axis", g.x_axis), ("--y-side", g.y_side)):
        if value is not None and value not in known:
            raise SurveyError(f"{name} {value}: no such anchor (anchors: {ids})")
    for a in settings.heights_m:
        if a not in known:
            raise SurveyError(f"--height {a}: no such anchor (anchors: {ids})")
    if (g.origin is None) != (g.x_axis is None):
        raise SurveyError("--origin and --x-axis go together (the frame needs both)")
    if g.y_side is not None and g.origin is None:
        raise SurveyError("--y-side needs --origin and --x-axis")
    chosen = [v for v in (g.origin, g.x_axis, g.y_side) if v is not None]
    if len(set(chosen)) != len(chosen):
        raise SurveyError("--origin, --x-axis and --y-side must be three different anchors")


def without_distance_term(model: RangeModel, uwb: Sequence[UwbRanges],
                          pairs: Sequence[AnchorRanges]
                          ) -> tuple[list[UwbRanges], list[AnchorRanges]]:
    """The tag's and the anchors' ranges less the config's distance term (``[range_model]
    log_distance_m``: a DW1000's range grows ``k ln(d / 1 m)`` beyond the distance, which
    would stretch the layout). The anchors' delays are not taken off: calibrated beside the
    tag's direction term, they would bias the heights without it; the survey estimates its
    own (``range_offsets``)."""
    def off(r: float) -> float:
        return model.distance_m(r) if math.isfinite(r) else r

    return ([dataclasses.replace(m, ranges=tuple(dataclasses.replace(r, range_m=off(r.range_m))
                                                 for r in m.ranges)) for m in uwb],
            [dataclasses.replace(m, pairs=tuple(dataclasses.replace(p, range_m=off(p.range_m))
                                                for p in m.pairs)) for m in pairs])


def survey(configured: Mapping[int, Sequence[float]], uwb: Sequence[UwbRanges],
           anchor_ranges: Sequence[AnchorRanges], settings: Settings | None = None) -> Survey:
    """Survey the anchors (see the module's text): ``configured``, the config's anchors;
    ``uwb``, the tag's ranges; ``anchor_ranges``, anchor-to-anchor reports."""
    begun = time.perf_counter()
    settings = settings or Settings()
    if not settings.prior_sigma_m > 0:
        raise SurveyError(f"--prior-sigma {settings.prior_sigma_m:g}: must be more than 0")
    config = {int(a): np.array(p, dtype=float) for a, p in configured.items()}
    pairs = reduce_pairs(anchor_ranges)
    pair_ids = {a for p in pairs for a in (p.anchor_a, p.anchor_b)}
    known = set(config) | pair_ids
    _check_ids(settings, known)
    rows_of = {a: i for i, a in enumerate(sorted(config))}
    messages = usable(uwb, rows_of, settings.max_range_m)
    tag_mode = sum(len(kept) for _, kept in messages) > 0
    if not tag_mode and not pairs:
        raise SurveyError("nothing to survey from: no tag ranges to configured anchors and no "
                          "anchor-to-anchor ranges")
    notes: list[str] = []
    if tag_mode:
        unknown = sorted({r.anchor_id for m in uwb for r in m.ranges} - set(config))
        if unknown:
            notes.append(f"ranges to anchors not in the config left out: "
                         f"{', '.join(map(str, unknown))}")
    ids = sorted(config) if tag_mode else sorted(known)
    if tag_mode and pair_ids - set(config):
        notes.append("anchor-to-anchor ranges to anchors not in the config left out: "
                     + ", ".join(map(str, sorted(pair_ids - set(config)))))
        pairs = [p for p in pairs if p.anchor_a in config and p.anchor_b in config]
    # heights: --height, else the config; anchor-to-anchor only: every anchor needs one
    z = {a: float(settings.heights_m.get(a, config[a][2] if a in config else math.nan))
         for a in ids}
    missing = [a for a in ids if not math.isfinite(z[a])]
    if missing:
        raise SurveyError(f"anchor {missing[0]} has anchor-to-anchor ranges but no height: give "
                          f"--height {missing[0]}=Z (or put it in the config)")
    # the configured positions in the output frame: the priors
    prior = np.full((len(ids), 3), np.nan)
    for i, a in enumerate(ids):
        if a in config:
            prior[i] = config[a]
    g = settings.gauge
    R, t = np.eye(3), np.zeros(3)
    if g.user:
        assert g.origin is not None and g.x_axis is not None
        for option, a in (("--origin", g.origin), ("--x-axis", g.x_axis)):
            if config and a not in config:
                raise SurveyError(f"{option} {a}: anchor {a} is not in the config, so the "
                                  "configured anchors cannot be carried into the frame it "
                                  "defines; add it to the config or choose another")
        if config:
            R, t = frame_of(config[g.origin], config[g.x_axis])
        prior = (prior - t) @ R.T
        if g.y_side is not None and g.y_side in config and g.x_axis in config:
            x_point = prior[ids.index(g.x_axis)]
            if side_of(prior[ids.index(g.y_side)], x_point) < 0:
                raise SurveyError(
                    f"--y-side {g.y_side}: the config puts anchor {g.y_side} on the -y (right) "
                    f"side of {g.origin} -> {g.x_axis}; a frame with z up and anchor "
                    f"{g.y_side} at +y would be a mirror image: give an anchor on the left of "
                    f"{g.origin} -> {g.x_axis}")
    for i, a in enumerate(ids):
        if a in settings.heights_m:
            prior[i, 2] = settings.heights_m[a]
    if tag_mode:
        start = prior.copy()
        free = np.ones((len(ids), 3), dtype=bool)
    else:
        start, free = pairs_start(ids, pairs, z, prior, settings, notes)
    if not tag_mode:
        start[:, 2] = [z[a] for a in ids]
    # anchors on one plane: neither their ranges to each other nor those of a tag on one
    # side see their heights (held); otherwise estimated
    placed = free[:, 0]
    heights_held = bool(placed.sum() < 4 or coplanar(start[placed], COPLANAR_M))
    free[:, 2] = placed & (not heights_held)
    for i, a in enumerate(ids):
        if a in settings.heights_m:
            free[i, 2] = False
            start[i, 2] = settings.heights_m[a]
    if g.user:
        assert g.origin is not None and g.x_axis is not None
        io, ix = ids.index(g.origin), ids.index(g.x_axis)
        start[io, :2] = 0.0
        start[ix, 1] = 0.0
        free[io, :2] = False
        free[ix, 1] = False
    reached = reached_by(ids, pairs, messages if tag_mode else [], rows_of)
    # an anchor nothing reaches keeps its prior: not estimated
    for i, a in enumerate(ids):
        if a not in reached:
            free[i] = False
    tag = None
    if tag_mode:
        tag = tag_data(messages, start, settings)
        if tag is None:
            raise SurveyError("no tag position could be solved from the ranges (too few ranges "
                              f"per epoch: {MIN_EPOCH_RANGES} anchors at least)")
    index = {a: i for i, a in enumerate(ids)}
    if tag is not None:  # the tag's path alone first, robustly: NLOS out of the start
        alone = Problem(ids=ids, start=start, free=np.zeros_like(free), prior=prior,
                         prior_sigma_m=settings.prior_sigma_m, tag=tag,
                         range_sigma_m=settings.range_sigma_m,
                         pair_i=np.zeros(0, dtype=np.intp), pair_j=np.zeros(0, dtype=np.intp),
                         pair_m=np.zeros(0), pair_sigma=np.zeros(0), offsets=False,
                         offset_sigma_m=settings.offset_sigma_m)
        tag.knots = solve(alone)[0].reshape(-1, 3)
    problem = Problem(
        ids=ids, start=start, free=free, prior=prior, prior_sigma_m=settings.prior_sigma_m,
        tag=tag, range_sigma_m=settings.range_sigma_m,
        pair_i=np.array([index[p.anchor_a] for p in pairs], dtype=np.intp),
        pair_j=np.array([index[p.anchor_b] for p in pairs], dtype=np.intp),
        pair_m=np.array([p.median_m for p in pairs]),
        pair_sigma=np.array([p.sigma_m for p in pairs]),
        offsets=settings.range_offsets and tag_mode, offset_sigma_m=settings.offset_sigma_m)
    confined = None
    if tag_mode and problem.n_anchor and bool((~np.isnan(prior[free])).all()):
        V, V_rest = trusted_directions(problem)
        confined = Confined(problem, V, prior[free])
        xr, jac, nfev = solve(confined)
        x = confined.full(xr)
        if V_rest.shape[1]:
            notes.append(f"{V_rest.shape[1]} of the {problem.n_anchor} anchor coordinates' "
                         "directions are fixed by the ranges less than twice as well as by "
                         "the configured positions: left as configured"
                         + (" (among them where the whole layout sits, which no range "
                            "sees)" if not g.user else ""))
    else:
        x, jac, nfev = solve(problem)
    _, A, b = problem.unpack(x)
    f = problem.residuals(x)
    sigma0 = 1.0
    rms = math.nan
    downweighted = 0
    if tag is not None:
        ft = f[:problem.n_tag]
        sigma0 = max(MAD_TO_SIGMA * float(np.median(np.abs(ft - np.median(ft)))), 1e-3)
        rms = sigma0 * settings.range_sigma_m
        downweighted = int(np.sum(np.abs(ft) > 3 * sigma0))
    if confined is None:
        cov = anchor_covariance(problem, jac) * sigma0**2
    else:  # back to the anchor coordinates; the directions left out keep the priors' σ
        k, na = confined.n_anchor, problem.n_anchor
        cr = anchor_covariance(confined, jac) * sigma0**2
        cov = np.zeros((problem.n - 3 * problem.K,) * 2)
        V = confined.V
        cov[:na, :na] = V @ cr[:k, :k] @ V.T + V_rest @ V_rest.T * problem.prior_sigma_m**2
        cov[na:, na:] = cr[k:, k:]
        cov[:na, na:] = V @ cr[:k, k:]
        cov[na:, :na] = cov[:na, na:].T
    var = np.zeros((len(ids), 3))
    var[free] = np.diag(cov)[:problem.n_anchor]
    free_cov = cov[:problem.n_anchor, :problem.n_anchor]
    layout, frame = (layout_part(free_cov, A, free, g.user) if problem.n_anchor
                     else (0.0, 0.0))
    off_var = (np.diag(cov)[problem.offset_col - 3 * problem.K] if problem.offsets
               else np.zeros(0))
    estimates = {}
    for i, a in enumerate(ids):
        sig = np.sqrt(np.maximum(var[i], 0.0))
        if not free[i].any() and a in config:
            sig = np.where(free[i], sig, 0.0)
            if a not in reached:  # unchanged from its prior: as uncertain as the tape
                sig = np.array([settings.prior_sigma_m] * 3)
                if a in settings.heights_m:
                    sig[2] = 0.0
        estimates[a] = AnchorEstimate(
            a, _vec(A[i]), _vec(sig), _vec(config[a]) if a in config else None,
            _vec(prior[i]) if a in config else None, a in reached,
            float(b[i]) if problem.offsets else None,
            math.sqrt(max(float(off_var[i]), 0.0)) if problem.offsets else None)
    not_reached = [a for a in ids if a not in reached]
    if not_reached:
        notes.append("no range reaches anchor(s) " + ", ".join(map(str, not_reached))
                     + ": kept as configured" + (" (carried into the frame)" if g.user else ""))
    if heights_held:
        notes.append("heights held at " + ("--height / " if settings.heights_m else "")
                     + "the config's: ranges between anchors on one plane do not observe "
                     "them")
    gauge = (f"anchor {g.origin} at the origin, {g.x_axis} on +x"
             + (f", {g.y_side} on +y" if g.y_side is not None else "")
             + (f"; the rest tied to the configured positions carried into that frame "
                f"(σ {settings.prior_sigma_m:g} m)") if g.user
             else f"the config's frame (every anchor tied to its configured position, "
                  f"σ {settings.prior_sigma_m:g} m)")
    turn_deg = math.degrees(math.atan2(-R[0, 1], R[0, 0]))
    if g.user and config and (abs(t[0]) + abs(t[1]) > 0.0005 or abs(turn_deg) > 0.005):
        notes.append(f"the frame: the config's coordinates shifted by ({-t[0] + 0:+.3f}, "
                     f"{-t[1] + 0:+.3f}) m and turned by {round(turn_deg, 2) + 0:+.2f}° about z; "
                     "Δ is from the configured positions carried into it")
    return Survey(
        estimates, ("tag ranges" + (" and anchor-to-anchor ranges" if pairs else "")
                    if tag_mode else "anchor-to-anchor ranges"),
        gauge, problem.n_tag, problem.K, pairs, rms, sigma0, downweighted, layout, frame, nfev,
        time.perf_counter() - begun, notes, (float(t[0]), float(t[1])), turn_deg, g.user)


def _vec(v: Array) -> Vec3:
    return (float(v[0]), float(v[1]), float(v[2]))
