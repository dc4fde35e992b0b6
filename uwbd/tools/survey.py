"""``uwbd survey``: the anchor positions, from the ranges in a log.

Tape-measured anchors are off by 5-20 cm; that error reaches every fix. Two kinds of range
fix the anchors' layout:

* **anchor-to-anchor ranges** (TREK1000 ``ma`` reports, :class:`~drivers.frames.AnchorRanges`
  on ``/anchor_ranges`` or decoded from the raw bytes): each pair's repeated ranges are
  reduced to their median (an NLOS range or a glitch does not move it) and the standard
  error of that median (1.2533 x 1.4826 MAD / √n, at least 2 mm). Classical
  multilateration places the anchors from the horizontal distances alone, one after
  another (the best-connected pair on an axis, then each anchor by two-circle
  intersection, the side chosen by a third placed neighbour, and Gauss-Newton against all
  of them), independently of the configured positions; the layout is then carried into the
  output frame and one least-squares adjustment takes every pair at once (least squares:
  the medians are robust already). The TREK1000 reports A0-A1, A0-A2 and A1-A2 only: 3
  ranges fix the triangle A0 A1 A2 (its 3 side lengths) exactly, with nothing left over to
  check them; they fix nothing about A3 (kept as configured), the heights, where the
  triangle sits and points (the gauge, below) or its mirror image, and an antenna-delay
  error scales the triangle whatever the averaging.
* **a moving tag's ranges** (``UwbRanges``): one batch nonlinear least squares
  (:func:`scipy.optimize.least_squares`, trust region with LSMR, an analytic sparse
  Jacobian) over the tag's path and the anchors together: one tag position per UWB epoch
  with 4 ranges or more (an epoch with 3 says nothing about the anchors), or, for one
  asynchronous range per message, a position every 0.2 s with the tag moving linearly
  between them; optionally (``range_offsets``) a range offset per anchor (its antenna
  delay), tied to 0 with ``[fusion] range_bias_sigma_m``. It starts from the configured
  anchors, and takes the log's anchor-to-anchor ranges too. The loss on the tag's ranges is
  ``arctan`` at 2 σ (redescending: a range 6 σ off weighs 1/80 of a good one), since NLOS
  comes in bursts that bias ranges for seconds and ``soft_l1`` or Huber still let them pull
  the layout by decimetres; the tag's path is first solved alone (anchors held) with the
  same loss, so that the joint solve starts with the NLOS ranges already recognised. A
  safeguard, measured necessary (``benchmarks/bench_survey.py``): a tag position per
  epoch from few ranges biases the anchors along the directions the ranges fix poorly (a
  Neyman-Scott effect: thousands of nuisance positions), and ceiling anchors over a ground
  robot have such directions (the layout's scale against the tag's height, a twist of the
  heights). So the ranges' own information about the anchors is computed at the start (the
  tag positions and offsets marginalised, the priors' information taken out) and the anchors
  move only along its eigen-directions that the ranges fix at least twice as well (in σ) as
  the priors; the rest stays as configured, and says so.

**Heights** are held at the config's (or ``--height``) when the anchors lie on one plane
within 0.3 m RMS, as ceiling anchors do: a range's change with a height difference dz is
dz/r, nothing at dz = 0, so ranges within the plane do not see heights, and a tag on one
side of it sees them hardly (what it sees, a twist of the heights, the NLOS bias pushes:
measured worse than the tape). Otherwise they are estimated (tied to the configured ones
like every coordinate, below). Heights are what a laser or a tape held vertically measures
well: ``--height`` for each anchor is the way to get them right.

**The gauge.** Ranges fix the layout only up to a rigid motion (3 translations, 3
rotations) and a mirror image. Two ways to fix it, both offered:

* by default every configured coordinate is a measurement of that anchor, σ
  ``prior_sigma_m`` (0.2 m): this ties the layout softly to where it was tape-measured,
  keeps the config's frame (the frame the robot's map is in) and adds what the tape
  measure knows about the shape. Where the layout as a whole sits is then known only to
  about σ/√n (the tape measure's average error), and that part of the tape error stays in
  the result: ranges cannot see it.
* ``--origin O --x-axis X [--y-side Y]``: the user's frame: O at (0, 0), X on the +x axis
  (its y = 0), Y on the +y side (by default the side the config puts it on); these hold
  exactly, and the priors, carried into that frame, fix the rest (the vertical and the
  tilt, softly: the heights' average). The config is carried into that frame first
  (translated and turned so O and X are where the frame puts them).

A ``--height`` holds that anchor's height exactly. A frame is right-handed with z up: a
``--y-side`` anchor that the config puts on the -y side is refused (it would mirror the
frame).

**Uncertainty**: the covariance σ0² (JᵀJ)⁻¹ at the solution (J with the robust loss's
weights; the tag positions eliminated by the Schur complement), σ0 the residuals' robust
scale (1.4826 MAD, in units of the range σ) for tag ranges, 1 for anchor-to-anchor ranges
(whose σ is their own scatter); the directions left as configured keep the priors' σ; 1-σ
per axis. It holds the range noise only: an NLOS detour held for seconds or an antenna
delay is not in it. In the default gauge it includes where the frame sits;
``layout_sigma_m`` is the part that is the anchors relative to each other (the covariance
with the rigid motions projected out).

Needs scipy (the ``tools`` extra).
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from drivers import PARSERS
from drivers.frames import AnchorRanges, Frame, UwbRanges
from uwbd.codec import frame_from_dict
from uwbd.config import ConfigError, parse
from uwbd.config.overrides import write_toml
from uwbd.config.schema import anchor_id
from uwbd.fusion.lsq import coplanar, multilaterate
from uwbd.fusion.mirror import MirrorSide
from uwbd.fusion.rotation import Array
from uwbd.logs.mcaplog import LogContents

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Vec3 = tuple[float, float, float]
WINDOW_S = 0.2  # asynchronous single ranges: one tag position this often
MIN_EPOCH_RANGES = 4  # an epoch with 3 ranges fits any anchors: it says nothing about them
# the tag's ranges: arctan (redescending: a range 6 σ off weighs 1/80 of a good one; NLOS),
# quadratic to about this many σ
ROBUST_SCALE = 2.0
MAX_EVALUATIONS = 200
TRUST = 2.0  # a direction is moved where the ranges fix it to half the prior's σ or better
MAD_TO_SIGMA = 1.4826
MEDIAN_EFFICIENCY = 1.2533  # the standard error of a median is this times the mean's
PAIR_SIGMA_FLOOR_M = 0.002  # a pair's σ never below 2 mm (its ranges are mm integers)
COPLANAR_M = 0.3  # anchors this close to one plane (RMS): their heights are held
SIDE_TOLERANCE_M = 0.05  # an anchor this close to the x axis is on neither side
SIDE_TOLERANCE_RAD = 0.01  # ... or this close in angle (a long baseline)


class SurveyError(ValueError):
    """What the user asked for cannot be surveyed (one line: the CLI's exit 2)."""


@dataclass(frozen=True)
class Gauge:
    """The frame the anchors are given in: ``origin`` at (0, 0), ``x_axis`` on +x,
    ``y_side`` on the +y side; ``origin`` ``None``: the config's frame (priors only)."""

    origin: int | None = None
    x_axis: int | None = None
    y_side: int | None = None

    @property
    def user(self) -> bool:
        return self.origin is not None


@dataclass(frozen=True)
class Settings:
    gauge: Gauge = Gauge()
    heights_m: Mapping[int, float] = field(default_factory=dict)  # held exactly
    prior_sigma_m: float = 0.2
    range_sigma_m: float = 0.1
    range_offsets: bool = False
    offset_sigma_m: float = 0.1
    tag_side: str = "auto"
    height_range_m: tuple[float, float] | None = None
    max_range_m: float = 100.0
    window_s: float = WINDOW_S


@dataclass(frozen=True)
class PairRange:
    """One anchor pair's repeated ranges, reduced: median, its standard error (1.2533 ×
    1.4826 MAD / √n), and how many were more than 5 robust σ off the median."""

    anchor_a: int
    anchor_b: int
    n: int
    median_m: float
    sigma_m: float
    outliers: int


@dataclass(frozen=True)
class AnchorEstimate:
    """``position_m`` in the output frame, ``sigma_m`` its 1-σ per axis (0 where the gauge
    or ``--height`` holds it); ``configured_m`` as in the config (its frame), ``prior_m``
    the config carried into the output frame; ``surveyed``: ranges reached it."""

    anchor: int
    position_m: Vec3
    sigma_m: Vec3
    configured_m: Vec3 | None
    prior_m: Vec3 | None
    surveyed: bool
    range_offset_m: float | None = None
    range_offset_sigma_m: float | None = None

    @property
    def change_m(self) -> Vec3 | None:
        """From the configured position (carried into the output frame) to the surveyed
        one."""
        if self.prior_m is None:
            return None
        p, c = self.position_m, self.prior_m
        return (p[0] - c[0], p[1] - c[1], p[2] - c[2])


@dataclass
class Survey:
    anchors: dict[int, AnchorEstimate]
    source: str  # "anchor-to-anchor ranges" or "tag ranges" (+ pairs)
    gauge: str
    tag_ranges: int = 0
    tag_positions: int = 0
    pairs: list[PairRange] = field(default_factory=list)
    residual_rms_m: float = math.nan  # tag ranges: robust RMS (1.4826 MAD), m
    sigma0: float = 1.0
    downweighted: int = 0  # tag ranges more than 3 σ off at the solution
    layout_sigma_m: float = math.nan  # RMS 3-D 1-σ of the anchors relative to each other
    frame_sigma_m: float = math.nan  # RMS 3-D 1-σ of where the layout sits (soft gauge)
    iterations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    # the config's frame -> the output frame: p' = R(turn) (p - shift); zero in the config's
    frame_shift_m: tuple[float, float] = (0.0, 0.0)
    frame_turn_deg: float = 0.0
    user_frame: bool = False  # --origin/--x-axis: x, y and the heading held, not soft

    def positions(self) -> dict[int, Vec3]:
        return {a: e.position_m for a, e in sorted(self.anchors.items())}


# -- reading a log -------------------------------------------------------------------------

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


def reduce_pairs(reports: Sequence[AnchorRanges]) -> list[PairRange]:
    """Each pair's ranges (non-finite and non-positive ones dropped) as a :class:`PairRange`."""
    ranges: dict[tuple[int, int], list[float]] = {}
    for report in reports:
        for p in report.pairs:
            if math.isfinite(p.range_m) and p.range_m > 0 and p.anchor_a != p.anchor_b:
                key = (min(p.anchor_a, p.anchor_b), max(p.anchor_a, p.anchor_b))
                ranges.setdefault(key, []).append(p.range_m)
    out = []
    for (a, b), values in sorted(ranges.items()):
        r = np.array(values)
        med = float(np.median(r))
        spread = MAD_TO_SIGMA * float(np.median(np.abs(r - med)))
        outliers = int(np.sum(np.abs(r - med) > 5 * spread)) if spread > 0 else 0
        se = MEDIAN_EFFICIENCY * spread / math.sqrt(len(r))
        out.append(PairRange(a, b, len(r), med, max(se, PAIR_SIGMA_FLOOR_M), outliers))
    return out


# -- the gauge -----------------------------------------------------------------------------

def _frame_of(origin: Array, x_point: Array) -> tuple[Array, Array]:
    """The rotation (about z) and translation taking ``origin`` to (0, 0, z) and
    ``x_point`` onto the +x axis: p' = R (p - t)."""
    heading = math.atan2(x_point[1] - origin[1], x_point[0] - origin[0])
    c, s = math.cos(heading), math.sin(heading)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.array([origin[0], origin[1], 0.0])
    return R, t


def _side(p: Array, x_point: Array) -> int:
    """+1, -1: which side of the +x axis ``p`` is on (in the gauge frame); 0: too close to
    it to tell (5 cm, or 0.01 rad seen from the middle of origin and ``x_point``)."""
    off_axis = abs(float(p[0]) - float(x_point[0]) / 2)
    if abs(p[1]) < max(SIDE_TOLERANCE_M, SIDE_TOLERANCE_RAD * off_axis):
        return 0
    return 1 if p[1] > 0 else -1


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


# -- the adjustment ------------------------------------------------------------------------

@dataclass
class _TagData:
    """Tag ranges ready for the adjustment: range j measured ``range_m[j]`` to anchor
    ``anchor[j]`` (row index) from the tag at ``(1 - alpha) P[k0] + alpha P[k1]``."""

    knots: Array  # K x 3 initial tag positions
    times: Array  # K, s
    anchor: npt.NDArray[np.intp]
    k0: npt.NDArray[np.intp]
    k1: npt.NDArray[np.intp]
    alpha: Array
    range_m: Array


@dataclass
class _Problem:
    ids: list[int]  # row i of the anchor arrays is anchor ids[i]
    start: Array  # N x 3 initial positions (also the held values)
    free: npt.NDArray[np.bool_]  # N x 3: which coordinates are estimated
    prior: Array  # N x 3 (nan: no prior)
    prior_sigma_m: float
    tag: _TagData | None
    range_sigma_m: float
    pair_i: npt.NDArray[np.intp]
    pair_j: npt.NDArray[np.intp]
    pair_m: Array
    pair_sigma: Array
    offsets: bool
    offset_sigma_m: float

    def __post_init__(self) -> None:
        self.K = 0 if self.tag is None else len(self.tag.knots)
        self.N = len(self.ids)
        col = np.full((self.N, 3), -1, dtype=np.intp)
        col[self.free] = 3 * self.K + np.arange(int(self.free.sum()))
        self.anchor_col = col
        self.n_anchor = int(self.free.sum())
        self.offset_col = (3 * self.K + self.n_anchor + np.arange(self.N) if self.offsets
                           else np.zeros(0, dtype=np.intp))
        self.n = 3 * self.K + self.n_anchor + len(self.offset_col)
        self.prior_rows = np.flatnonzero((self.free & ~np.isnan(self.prior)).ravel())
        self._structure()

    def x0(self) -> Array:
        parts = [self.tag.knots.ravel() if self.tag is not None else np.zeros(0),
                 self.start[self.free], np.zeros(len(self.offset_col))]
        return np.concatenate(parts)

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        P = x[:3 * self.K].reshape(self.K, 3)
        A = self.start.copy()
        A[self.free] = x[3 * self.K:3 * self.K + self.n_anchor]
        b = x[self.offset_col] if self.offsets else np.zeros(self.N)
        return P, A, b

    def _structure(self) -> None:
        """Row and column of every Jacobian entry (fixed: only the values change)."""
        rows: list[npt.NDArray[np.intp]] = []
        cols: list[npt.NDArray[np.intp]] = []
        self.n_tag = 0 if self.tag is None else len(self.tag.range_m)
        r0 = 0
        if self.tag is not None:
            t = self.tag
            j = np.arange(self.n_tag)
            for k in (t.k0, t.k1):  # the two knots' x, y, z
                rows.append(np.repeat(j, 3))
                cols.append((3 * k[:, None] + np.arange(3)).ravel())
            ac = self.anchor_col[t.anchor]  # n_tag x 3
            self._tag_anchor_mask = (ac >= 0).ravel()
            rows.append(np.repeat(j, 3)[self._tag_anchor_mask])
            cols.append(ac.ravel()[self._tag_anchor_mask])
            if self.offsets:
                rows.append(j)
                cols.append(self.offset_col[t.anchor])
            r0 = self.n_tag
        self.n_pair = len(self.pair_m)
        if self.n_pair:
            j = r0 + np.arange(self.n_pair)
            self._pair_masks = []
            for idx in (self.pair_i, self.pair_j):
                ac = self.anchor_col[idx]
                mask = (ac >= 0).ravel()
                self._pair_masks.append(mask)
                rows.append(np.repeat(j, 3)[mask])
                cols.append(ac.ravel()[mask])
            r0 += self.n_pair
        self.n_prior = len(self.prior_rows)
        rows.append(r0 + np.arange(self.n_prior))
        cols.append(self.anchor_col.ravel()[self.prior_rows])
        r0 += self.n_prior
        if self.offsets:
            rows.append(r0 + np.arange(self.N))
            cols.append(self.offset_col)
            r0 += self.N
        self.m = r0
        self._rows = np.concatenate(rows)
        self._cols = np.concatenate(cols)

    def residuals(self, x: Array) -> Array:
        P, A, b = self.unpack(x)
        out: list[Array] = []
        if self.tag is not None:
            t = self.tag
            p = (1 - t.alpha)[:, None] * P[t.k0] + t.alpha[:, None] * P[t.k1]
            d = np.linalg.norm(p - A[t.anchor], axis=1)
            out.append((d + b[t.anchor] - t.range_m) / self.range_sigma_m)
        if self.n_pair:
            d = np.linalg.norm(A[self.pair_i] - A[self.pair_j], axis=1)
            out.append((d - self.pair_m) / self.pair_sigma)
        out.append((A.ravel()[self.prior_rows] - self.prior.ravel()[self.prior_rows])
                   / self.prior_sigma_m)
        if self.offsets:
            out.append(b / self.offset_sigma_m)
        return np.concatenate(out)

    def jacobian(self, x: Array) -> Any:
        P, A, _ = self.unpack(x)
        vals: list[Array] = []
        if self.tag is not None:
            t = self.tag
            p = (1 - t.alpha)[:, None] * P[t.k0] + t.alpha[:, None] * P[t.k1]
            diff = p - A[t.anchor]
            u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
            u /= self.range_sigma_m
            vals += [((1 - t.alpha)[:, None] * u).ravel(), (t.alpha[:, None] * u).ravel(),
                     (-u).ravel()[self._tag_anchor_mask]]
            if self.offsets:
                vals.append(np.full(self.n_tag, 1 / self.range_sigma_m))
        if self.n_pair:
            diff = A[self.pair_i] - A[self.pair_j]
            u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
            u /= self.pair_sigma[:, None]
            vals += [u.ravel()[self._pair_masks[0]], (-u).ravel()[self._pair_masks[1]]]
        vals.append(np.full(self.n_prior, 1 / self.prior_sigma_m))
        if self.offsets:
            vals.append(np.full(self.N, 1 / self.offset_sigma_m))
        return scipy.sparse.csr_matrix((np.concatenate(vals), (self._rows, self._cols)),
                                       shape=(self.m, self.n))


def _loss(n_tag: int) -> Any:
    """The robust loss for scipy (ρ, ρ', ρ'' of z = f²): ``arctan`` at ``ROBUST_SCALE`` on the
    first ``n_tag`` rows (the tag's ranges: NLOS), least squares on the rest (the pairs'
    medians, already robust; the priors)."""
    c2 = ROBUST_SCALE**2

    def loss(z: Array) -> Array:
        out = np.empty((3, len(z)))
        out[0], out[1], out[2] = z, 1.0, 0.0
        u = z[:n_tag] / c2
        out[0, :n_tag] = c2 * np.arctan(u)
        out[1, :n_tag] = 1 / (1 + u**2)
        out[2, :n_tag] = -2 * u / (c2 * (1 + u**2) ** 2)
        return out
    return loss


def _solve(problem: _Problem | _Confined) -> tuple[Array, Any, int]:
    """The robust adjustment from the problem's start: the solution, the loss-weighted
    Jacobian there, the number of function evaluations."""
    result = scipy.optimize.least_squares(
        problem.residuals, problem.x0(), jac=problem.jacobian, method="trf",
        loss=_loss(problem.n_tag), x_scale="jac", tr_solver="lsmr", xtol=1e-10, ftol=1e-10,
        gtol=1e-10, max_nfev=MAX_EVALUATIONS)
    return np.asarray(result.x, dtype=float), result.jac, int(result.nfev)


def _anchor_covariance(problem: _Problem | _Confined, jac: Any) -> Array:
    """The covariance (JᵀJ)⁻¹ of everything but the tag positions (anchor coordinates and
    offsets), those eliminated by the Schur complement; in units of the
    residuals' σ."""
    J = scipy.sparse.csc_matrix(jac)
    H = (J.T @ J).tocsc()
    nt = 3 * problem.K
    Haa = H[nt:, nt:].toarray()
    if nt:
        Htt = H[:nt, :nt].tocsc()
        Hta = H[:nt, nt:].toarray()
        # a tag position no range reaches (it cannot happen: each knot has 4 ranges) would
        # make Htt singular; a tiny ridge keeps the factorisation alive
        Htt = Htt + scipy.sparse.identity(nt, format="csc") * 1e-12
        lu = scipy.sparse.linalg.splu(Htt)
        Haa = Haa - Hta.T @ lu.solve(Hta)
    return np.asarray(np.linalg.pinv(Haa, hermitian=True), dtype=float)


def _trusted_directions(problem: _Problem) -> tuple[Array, Array]:
    """The directions of the free anchor coordinates that the ranges fix at least ``TRUST``
    times better (in σ) than the priors, and the rest: the eigenvectors of the ranges' own
    information about the anchors (the tag positions and offsets marginalised; the
    priors' information taken out), at the start (the configured layout). The adjustment
    moves the anchors in the first only: a direction the ranges hardly fix is where model
    errors (NLOS, the bias of a tag position estimated per epoch from few ranges) push the
    solution, far, and where that far-off solution then looks well fixed."""
    na = problem.n_anchor
    cov = _anchor_covariance(problem, problem.jacobian(problem.x0()))
    info = np.linalg.pinv(cov[:na, :na], hermitian=True)
    prior = np.zeros(na)
    prior[problem.anchor_col.ravel()[problem.prior_rows] - 3 * problem.K] = \
        1 / problem.prior_sigma_m**2
    lam, V = np.linalg.eigh(0.5 * (info + info.T) - np.diag(prior))
    keep = lam * problem.prior_sigma_m**2 >= TRUST**2
    return V[:, keep], V[:, ~keep]


class _Confined:
    """A problem whose free anchor coordinates move from ``origin`` along the columns of
    ``V`` only: x = T xr + shift."""

    def __init__(self, problem: _Problem, V: Array, origin: Array) -> None:
        self.problem, self.V, self.origin = problem, V, origin
        self.K = problem.K
        self.n_tag = problem.n_tag
        nt, na, k = 3 * problem.K, problem.n_anchor, V.shape[1]
        rest = problem.n - nt - na
        self.n_anchor = k
        rows = [np.arange(nt), nt + np.repeat(np.arange(na), k), nt + na + np.arange(rest)]
        cols = [np.arange(nt), nt + np.tile(np.arange(k), na), nt + k + np.arange(rest)]
        vals = [np.ones(nt), V.ravel(), np.ones(rest)]
        self.T = scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(problem.n, nt + k + rest))
        self.shift = np.zeros(problem.n)
        self.shift[nt:nt + na] = origin

    def full(self, xr: Array) -> Array:
        return np.asarray(self.T @ xr + self.shift, dtype=float)

    def x0(self) -> Array:
        x = self.problem.x0()
        nt, na = 3 * self.K, self.problem.n_anchor
        return np.concatenate([x[:nt], self.V.T @ (x[nt:nt + na] - self.origin),
                               x[nt + na:]])

    def residuals(self, xr: Array) -> Array:
        return self.problem.residuals(self.full(xr))

    def jacobian(self, xr: Array) -> Any:
        return (self.problem.jacobian(self.full(xr)) @ self.T).tocsr()


def _layout_part(cov: Array, A: Array, free: npt.NDArray[np.bool_], vertical_only: bool
                 ) -> tuple[float, float]:
    """RMS 3-D 1-σ of the anchors relative to each other (the motions of the whole layout
    that the ranges cannot see projected out of the free coordinates' covariance) and of
    the rest (where the layout sits). In the config's frame those are the 6 rigid motions;
    in the user's (``vertical_only``: x, y and the heading held) the height and the tilts."""
    n = len(A)
    c = A.mean(axis=0)
    G = np.zeros((n, 3, 6))
    for k in range(3):
        G[:, k, k] = 1.0
    for k, axis in enumerate(np.eye(3)):
        G[:, :, 3 + k] = np.cross(axis, A - c)
    if vertical_only:  # a shift up and the two tilts, as they move the heights
        G = G[:, :, [2, 3, 4]]
        G[:, :2, :] = 0.0
    Gf = G.reshape(3 * n, -1)[free.ravel()]
    U, s, _ = np.linalg.svd(Gf, full_matrices=False)
    Q = U[:, s > 1e-9 * max(float(s.max()), 1e-300)] if s.size else U[:, :0]
    proj = np.eye(len(Gf)) - Q @ Q.T
    shape = proj @ cov @ proj
    total, inner = float(np.trace(cov)), float(np.trace(shape))
    return math.sqrt(max(inner, 0.0) / n), math.sqrt(max(total - inner, 0.0) / n)


# -- preparing the tag's ranges ------------------------------------------------------------

def _usable(uwb: Sequence[UwbRanges], anchors: Mapping[int, int], max_range_m: float
            ) -> list[tuple[int, list[tuple[int, float]]]]:
    """Per message: time and the (anchor row, range) it holds that can be used (finite,
    positive, within ``max_range_m``, to a known anchor, one per anchor)."""
    out = []
    for msg in uwb:
        seen: set[int] = set()
        kept = []
        for r in msg.ranges:
            row = anchors.get(r.anchor_id)
            if (row is None or row in seen or not math.isfinite(r.range_m)
                    or not 0 < r.range_m <= max_range_m):
                continue
            seen.add(row)
            kept.append((row, r.range_m))
        if kept:
            out.append((msg.t_ns, kept))
    return out


def _tag_data(messages: list[tuple[int, list[tuple[int, float]]]], A: Array,
              settings: Settings) -> _TagData | None:
    """Tag positions to solve for, and each range's place between them; the positions
    start from multilateration against the starting anchors."""
    mirror = MirrorSide(A, settings.tag_side, settings.height_range_m)
    side = mirror.sign if mirror.ambiguous else 1
    flat = coplanar(A) if len(A) >= 4 else True
    sizes = [len(kept) for _, kept in messages]
    epochs = bool(sizes) and float(np.median(sizes)) >= 3
    groups: list[tuple[float, list[tuple[int, float, float]]]] = []  # (t, [(row, r, t)])
    if epochs:
        for t_ns, kept in messages:
            if len(kept) >= MIN_EPOCH_RANGES:
                groups.append((t_ns / 1e9, [(a, r, t_ns / 1e9) for a, r in kept]))
    else:
        t0 = messages[0][0] / 1e9 if messages else 0.0
        windows: dict[int, list[tuple[int, float, float]]] = {}
        for t_ns, kept in messages:
            t = t_ns / 1e9
            slot = int((t - t0) // settings.window_s)
            windows.setdefault(slot, []).extend((a, r, t) for a, r in kept)
        for slot, items in sorted(windows.items()):
            if len({a for a, _, _ in items}) >= MIN_EPOCH_RANGES:
                groups.append((t0 + (slot + 0.5) * settings.window_s, items))
    knots: list[Array] = []
    times: list[float] = []
    members: list[list[tuple[int, float, float]]] = []
    previous: Array | None = None
    for t, items in groups:
        rows = np.array([a for a, _, _ in items])
        ranges = np.array([r for _, r, _ in items])
        start = previous if previous is not None else (
            mirror.start_point() if mirror.ambiguous else None)
        fix = multilaterate(A[rows], ranges, settings.range_sigma_m, x0=start,
                            side=side)
        if fix is None or (not flat and fix.rms_m > 10 * settings.range_sigma_m):
            fix = multilaterate(A[rows], ranges, settings.range_sigma_m, side=side)
        if fix is None or not np.all(np.isfinite(fix.position_m)):
            continue
        if mirror.ambiguous and mirror.side_of(fix.position_m) * side < 0:
            fix = multilaterate(A[rows], ranges, settings.range_sigma_m,
                                x0=mirror.reflect(fix.position_m), side=side) or fix
        previous = fix.position_m.copy()
        knots.append(fix.position_m.copy())
        times.append(t)
        members.append(items)
    if not knots:
        return None
    anchor: list[int] = []
    k0: list[int] = []
    k1: list[int] = []
    alpha: list[float] = []
    rng: list[float] = []
    T = np.array(times)
    for k, items in enumerate(members):
        for a, r, t in items:
            if epochs:
                lo, hi, w = k, k, 0.0
            else:  # between the knots around t, if they are neighbours in time
                lo = int(np.clip(np.searchsorted(T, t) - 1, 0, len(T) - 1))
                hi = min(lo + 1, len(T) - 1)
                gap = T[hi] - T[lo]
                if hi == lo or gap > 1.5 * settings.window_s or not T[lo] <= t <= T[hi]:
                    lo = hi = k
                    w = 0.0
                else:
                    w = (t - T[lo]) / gap
            anchor.append(a)
            k0.append(lo)
            k1.append(hi)
            alpha.append(w)
            rng.append(r)
    return _TagData(np.array(knots), np.array(times), np.array(anchor, dtype=np.intp),
                    np.array(k0, dtype=np.intp), np.array(k1, dtype=np.intp),
                    np.array(alpha), np.array(rng))


# -- anchor-to-anchor: classical multilateration -------------------------------------------

def _horizontal(pairs: Sequence[PairRange], z: Mapping[int, float]
                ) -> tuple[dict[tuple[int, int], float], list[str]]:
    notes = []
    h: dict[tuple[int, int], float] = {}
    for p in pairs:
        dz = z[p.anchor_a] - z[p.anchor_b]
        if p.median_m < abs(dz):
            notes.append(f"anchors {p.anchor_a}-{p.anchor_b}: range {p.median_m:.3f} m is "
                         f"shorter than their height difference {abs(dz):.3f} m; taken as "
                         "straight above each other")
        h[(p.anchor_a, p.anchor_b)] = h[(p.anchor_b, p.anchor_a)] = math.sqrt(
            max(p.median_m**2 - dz**2, 0.0))
    return h, notes


def _place(ids: list[int], h: Mapping[tuple[int, int], float]) -> dict[int, Array]:
    """The anchors' horizontal positions from their horizontal distances alone (a frame of
    their own: the best-connected pair on the x axis, the next anchor on +y)."""
    degree = {a: sum((a, b) in h for b in ids) for a in ids}
    first = max(((a, b) for a in ids for b in ids if a < b and (a, b) in h),
                key=lambda ab: (sum((ab[0], c) in h and (ab[1], c) in h for c in ids),
                                degree[ab[0]] + degree[ab[1]], h[ab]))
    placed = {first[0]: np.zeros(2), first[1]: np.array([h[first], 0.0])}
    while True:
        candidates = [a for a in ids if a not in placed
                      and sum((a, b) in h for b in placed) >= 2]
        if not candidates:
            return placed
        a = max(candidates, key=lambda c: (sum((c, b) in h for b in placed), -c))
        near = sorted((b for b in placed if (a, b) in h),
                      key=lambda b: -h[(a, b)])
        # the two placed neighbours farthest apart give the best-conditioned intersection
        b, c = max(((b, c) for b in near for c in near if b < c),
                   key=lambda bc: float(np.linalg.norm(placed[bc[0]] - placed[bc[1]])))
        options = _circles(placed[b], h[(a, b)], placed[c], h[(a, c)])
        others = [n for n in near if n not in (b, c)]
        if others:  # a third neighbour tells the two intersections apart
            options.sort(key=lambda p: _misfit(p, placed, h, a, others))
        elif len(placed) > 2:  # two neighbours only: the side nearest the layout's middle
            middle = np.mean(list(placed.values()), axis=0)
            options.sort(key=lambda p: -float(np.linalg.norm(p - middle)))
        else:
            options.sort(key=lambda p: -p[1])  # the first anchor off the axis: +y
        guess = options[0]
        rows = near
        fix = multilaterate(np.array([[*placed[n], 0.0] for n in rows]),
                            np.array([h[(a, n)] for n in rows]), 0.01,
                            x0=np.array([*guess, 0.0]), fixed_z=0.0, outlier_sigma=1e9)
        placed[a] = fix.position_m[:2] if fix is not None else guess


def _misfit(p: Array, placed: Mapping[int, Array], h: Mapping[tuple[int, int], float],
            a: int, others: Sequence[int]) -> float:
    return sum((float(np.linalg.norm(p - placed[n])) - h[(a, n)]) ** 2 for n in others)


def _circles(p: Array, r: float, q: Array, s: float) -> list[Array]:
    """Where circles (p, r) and (q, s) meet (touching, when noise keeps them apart)."""
    d = float(np.linalg.norm(q - p))
    if d < 1e-9:
        return [p + np.array([r, 0.0])]
    ex = (q - p) / d
    ey = np.array([-ex[1], ex[0]])
    x = (d * d + r * r - s * s) / (2 * d)
    y = math.sqrt(max(r * r - x * x, 0.0))
    return [p + x * ex + y * ey, p + x * ex - y * ey]


def _fit_2d(src: Array, dst: Array, mirror: bool) -> tuple[Array, Array, float]:
    """The rotation (and mirror) plus translation best taking ``src`` onto ``dst`` (2-D,
    least squares): x' = R x + t; and its RMS misfit."""
    s = src * np.array([1.0, -1.0]) if mirror else src
    cs, cd = s.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((s - cs).T @ (dst - cd))
    R = (U @ Vt).T
    if np.linalg.det(R) < 0:
        Vt[-1] *= -1
        R = (U @ Vt).T
    if mirror:
        R = R @ np.diag([1.0, -1.0])
    t = cd - R @ cs
    misfit = float(np.sqrt(np.mean(np.sum((src @ R.T + t - dst) ** 2, axis=1))))
    return R, t, misfit


# -- the survey ----------------------------------------------------------------------------

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
    messages = _usable(uwb, rows_of, settings.max_range_m)
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
            R, t = _frame_of(config[g.origin], config[g.x_axis])
        prior = (prior - t) @ R.T
        if g.y_side is not None and g.y_side in config and g.x_axis in config:
            x_point = prior[ids.index(g.x_axis)]
            if _side(prior[ids.index(g.y_side)], x_point) < 0:
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
        start, free = _pairs_start(ids, pairs, z, prior, settings, notes)
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
    reached = _reached(ids, pairs, messages if tag_mode else [], rows_of)
    # an anchor nothing reaches keeps its prior: not estimated
    for i, a in enumerate(ids):
        if a not in reached:
            free[i] = False
    tag = None
    if tag_mode:
        tag = _tag_data(messages, start, settings)
        if tag is None:
            raise SurveyError("no tag position could be solved from the ranges (too few ranges "
                              f"per epoch: {MIN_EPOCH_RANGES} anchors at least)")
    index = {a: i for i, a in enumerate(ids)}
    if tag is not None:  # the tag's path alone first, robustly: NLOS out of the start
        alone = _Problem(ids=ids, start=start, free=np.zeros_like(free), prior=prior,
                         prior_sigma_m=settings.prior_sigma_m, tag=tag,
                         range_sigma_m=settings.range_sigma_m,
                         pair_i=np.zeros(0, dtype=np.intp), pair_j=np.zeros(0, dtype=np.intp),
                         pair_m=np.zeros(0), pair_sigma=np.zeros(0), offsets=False,
                         offset_sigma_m=settings.offset_sigma_m)
        tag.knots = _solve(alone)[0].reshape(-1, 3)
    problem = _Problem(
        ids=ids, start=start, free=free, prior=prior, prior_sigma_m=settings.prior_sigma_m,
        tag=tag, range_sigma_m=settings.range_sigma_m,
        pair_i=np.array([index[p.anchor_a] for p in pairs], dtype=np.intp),
        pair_j=np.array([index[p.anchor_b] for p in pairs], dtype=np.intp),
        pair_m=np.array([p.median_m for p in pairs]),
        pair_sigma=np.array([p.sigma_m for p in pairs]),
        offsets=settings.range_offsets and tag_mode, offset_sigma_m=settings.offset_sigma_m)
    confined = None
    if tag_mode and problem.n_anchor and bool((~np.isnan(prior[free])).all()):
        V, V_rest = _trusted_directions(problem)
        confined = _Confined(problem, V, prior[free])
        xr, jac, nfev = _solve(confined)
        x = confined.full(xr)
        if V_rest.shape[1]:
            notes.append(f"{V_rest.shape[1]} of the {problem.n_anchor} anchor coordinates' "
                         "directions are fixed by the ranges less than twice as well as by "
                         "the configured positions: left as configured"
                         + (" (among them where the whole layout sits, which no range "
                            "sees)" if not g.user else ""))
    else:
        x, jac, nfev = _solve(problem)
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
        cov = _anchor_covariance(problem, jac) * sigma0**2
    else:  # back to the anchor coordinates; the directions left out keep the priors' σ
        k, na = confined.n_anchor, problem.n_anchor
        cr = _anchor_covariance(confined, jac) * sigma0**2
        cov = np.zeros((problem.n - 3 * problem.K,) * 2)
        V = confined.V
        cov[:na, :na] = V @ cr[:k, :k] @ V.T + V_rest @ V_rest.T * problem.prior_sigma_m**2
        cov[na:, na:] = cr[k:, k:]
        cov[:na, na:] = V @ cr[:k, k:]
        cov[na:, :na] = cov[:na, na:].T
    var = np.zeros((len(ids), 3))
    var[free] = np.diag(cov)[:problem.n_anchor]
    free_cov = cov[:problem.n_anchor, :problem.n_anchor]
    layout, frame = (_layout_part(free_cov, A, free, g.user) if problem.n_anchor
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


def _reached(ids: list[int], pairs: Sequence[PairRange],
             messages: list[tuple[int, list[tuple[int, float]]]],
             rows_of: Mapping[int, int]) -> set[int]:
    out = {a for p in pairs for a in (p.anchor_a, p.anchor_b)}
    row_ids = {row: a for a, row in rows_of.items()}
    for _, kept in messages:
        out.update(row_ids[row] for row, _ in kept)
    return out & set(ids)


def _pairs_start(ids: list[int], pairs: Sequence[PairRange], z: Mapping[int, float],
                 prior: Array, settings: Settings, notes: list[str]
                 ) -> tuple[Array, npt.NDArray[np.bool_]]:
    """Anchor-to-anchor ranges only: the anchors placed from their ranges alone, then put
    into the output frame (the user's, or the best fit to the configured positions). Heights
    are held (not free)."""
    h, said = _horizontal(pairs, z)
    notes += said
    placed = _place(ids, h)
    g = settings.gauge
    start = prior.copy()
    free = np.zeros((len(ids), 3), dtype=bool)
    names = sorted(placed)
    P = np.array([placed[a] for a in names])
    if g.user:
        assert g.origin is not None and g.x_axis is not None
        for a in (g.origin, g.x_axis):
            if a not in placed:
                raise SurveyError(f"anchor {a} cannot be placed from the anchor-to-anchor ranges "
                                  "(it needs ranges to 2 anchors placed before it)")
        o, x = placed[g.origin], placed[g.x_axis]
        R2, t2 = _frame_of(np.array([*o, 0.0]), np.array([*x, 0.0]))
        Q = (np.column_stack([P, np.zeros(len(P))]) - t2) @ R2.T
        side_anchor = g.y_side
        if side_anchor is None:  # the side the config puts the off-axis anchors on
            sides = [(abs(float(prior[ids.index(a), 1])), a) for a in names
                     if a not in (g.origin, g.x_axis) and not math.isnan(prior[ids.index(a), 1])
                     and _side(prior[ids.index(a)], prior[ids.index(g.x_axis)]) != 0]
            if not sides:
                raise SurveyError("which side of the x axis the anchors are on cannot be told: "
                                  "give --y-side ID (an anchor on the +y side)")
            side_anchor = max(sides)[1]
            want = _side(prior[ids.index(side_anchor)], prior[ids.index(g.x_axis)])
        else:
            want = 1
            if side_anchor not in placed:
                raise SurveyError(f"--y-side {side_anchor}: that anchor cannot be placed from "
                                  "the anchor-to-anchor ranges")
        got = _side(Q[names.index(side_anchor)], Q[names.index(g.x_axis)])
        if got == 0:
            raise SurveyError(f"anchor {side_anchor} lies on the x axis ({g.origin} -> "
                              f"{g.x_axis}): it cannot tell the sides apart; give another "
                              "--y-side")
        if got != want:
            Q[:, 1] *= -1
        for k, a in enumerate(names):
            start[ids.index(a), :2] = Q[k, :2]
    else:
        known = [a for a in names if not math.isnan(prior[ids.index(a), 0])]
        if len(known) < 3:
            raise SurveyError("the anchor-to-anchor ranges fix the layout but not where it is: "
                              "3 of its anchors need configured positions, or give --origin "
                              "and --x-axis")
        src = np.array([placed[a] for a in known])
        dst = np.array([prior[ids.index(a), :2] for a in known])
        fits = [_fit_2d(src, dst, m) for m in (False, True)]
        R2d, t2d, misfit = min(fits, key=lambda f: f[2])
        other = max(fits, key=lambda f: f[2])[2]
        if other < 1.5 * misfit or other - misfit < 0.05:
            raise SurveyError("the configured positions do not tell the layout from its mirror "
                              "image: give --origin, --x-axis and --y-side")
        for k, a in enumerate(names):
            start[ids.index(a), :2] = R2d @ P[k] + t2d
    for a in names:
        free[ids.index(a), :2] = True
    unplaced = [a for a in ids if a not in placed and a in {p.anchor_a for p in pairs}
                | {p.anchor_b for p in pairs}]
    if unplaced:
        notes.append("anchor(s) " + ", ".join(map(str, unplaced)) + " have ranges to one "
                     "anchor only: not placed")
    for a in unplaced:
        if math.isnan(prior[ids.index(a), 0]):
            raise SurveyError(f"anchor {a}: ranges to one other anchor only and no configured "
                              "position: it cannot be placed")
    return start, free


# -- output --------------------------------------------------------------------------------

def table(result: Survey) -> str:
    """The positions, their 1-σ and the change from the config, one line per anchor."""
    lines = [f"{'anchor':>6} {'x m':>9} {'y m':>9} {'z m':>8}  {'σx':>6} {'σy':>6} {'σz':>6}"
             f"  {'Δx':>7} {'Δy':>7} {'Δz':>7} {'|Δ|':>6}"
             + ("  offset m" if any(e.range_offset_m is not None
                                     for e in result.anchors.values()) else "")]
    for a, e in sorted(result.anchors.items()):
        x, y, zz = e.position_m
        sx, sy, sz = e.sigma_m
        line = f"{a:>6} {x:9.3f} {y:9.3f} {zz:8.3f}  {sx:6.3f} {sy:6.3f} {sz:6.3f}"
        d = e.change_m
        line += (f"  {d[0]:+7.3f} {d[1]:+7.3f} {d[2]:+7.3f} {math.hypot(*d):6.3f}"
                 if d is not None else f"  {'(not in the config)':>30}")
        if e.range_offset_m is not None and e.range_offset_sigma_m is not None:
            line += f"  {e.range_offset_m:+.3f} ± {e.range_offset_sigma_m:.3f}"
        if not e.surveyed:
            line += "  (no ranges: as configured)"
        lines.append(line)
    return "\n".join(lines)


def anchors_document(result: Survey, header: str) -> str:
    """A TOML file holding the surveyed ``[anchors]`` table (mm), checked by
    :func:`uwbd.config.parse`."""
    doc = {"anchors": {str(a): [round(v, 3) for v in p] for a, p in result.positions().items()}}
    text = _comment(header) + write_toml(doc)
    _check(text, "the anchors file")
    return text


def with_anchors(config_text: str, result: Survey, header: str, where: str) -> str:
    """``config_text`` with its ``[anchors]`` replaced by the surveyed ones (each keeping the
    key it was spelt with; anchors the survey did not see kept), as a TOML document that
    :func:`uwbd.config.parse` accepts. Comments are not kept."""
    try:
        doc = tomllib.loads(config_text)
    except tomllib.TOMLDecodeError as err:
        raise SurveyError(f"{where}: {err}") from err
    table_in = doc.get("anchors", {})
    if not isinstance(table_in, dict):
        raise SurveyError(f"{where}: anchors: not a table")
    out: dict[str, Any] = {}
    spelt = {anchor_id(k): k for k in table_in}
    positions = result.positions()
    for k, v in table_in.items():
        a = anchor_id(k)
        out[k] = [round(c, 3) for c in positions[a]] if a in positions else v
    for a, p in positions.items():
        if a not in spelt:
            out[str(a)] = [round(c, 3) for c in p]
    doc["anchors"] = out
    text = _comment(header) + write_toml(doc)
    _check(text, where)
    return text


def _comment(header: str) -> str:
    return "".join(f"# {line}\n" for line in header.splitlines()) + "\n"


def _check(text: str, where: str) -> None:
    try:
        parse(text, where)
    except ConfigError as err:  # a bug here, not the user's: say it as such
        raise RuntimeError(f"the written config would not parse: {err}") from err
