"""Range-model calibration (``uwbd calibrate-ranges``): the tag antenna's direction term and
the ranges' noise, from a log with ground truth (:mod:`uwbd.fusion.models.range_model`).

The recording: the tag (or the robot with it) carried for about 90 s through the anchors'
room under motion capture or another pose truth, turned through every heading and tilted a
little, near and far from each anchor. The truth may be the tag's own pose (lever arm 0, as
``uwbd import inrol`` writes a calibration recording) or the IMU's (the config's mounting
and lever arm take it to the antenna).

1. **Samples**: each range against the truth interpolated at its time (position linear,
   attitude by slerp), skipping ranges whose truth neighbours are more than 50 ms apart and
   motion-capture glitches (a jump and back faster than 5 m/s, or an attitude spike: turned
   and back faster than 20 rad/s). The residual ``e = r − |p_antenna − a|`` and the ray's
   direction ``u`` in the tag's axes.
2. **Fit** of ``e = o_anchor + Σ c_lm Y_lm(u) + k ln(d / 1 m)`` by robust maximum
   likelihood: iteratively reweighted least squares with a Cauchy loss (scale 2.385 × the
   residuals' robust σ). The per-anchor offsets ``o`` are each anchor's antenna delay (plus
   the tag's, common to all): a constant of the unit, which carries to another room with it
   (measured 1.6 cm RMS between the two INRoL rooms). Each coefficient's σ is a
   delete-one-block jackknife over 10 s blocks (the residuals are correlated over seconds:
   the textbook σ of independent samples would be several times too small).
   The distance term ``k`` (:mod:`uwbd.fusion.models.range_model`: a DW1000's timing
   depends on the received power) is written only where it lowers the held-out spread
   (step 3) and is at least 3 of its σ from zero.
3. **Held-out check**: the same fit on the first 70 % of the recording, scored on the last
   30 %, for every degree, without and with the distance term: the robust spread of the
   ranges. A degree that does not lower the held-out spread is not worth configuring.
4. **Noise** of what is left (:mod:`uwbd.tools.range_noise`): a robust σ of the core, the
   share of long and short ranges beyond 3 σ (NLOS only ever lengthens a range), the
   residuals' autocovariance split into
   white noise, a fast correlated part (what the filter's multipath states model) and a slow
   one (what constant delays would miss). The fast part is what the filter's multipath
   states are: written as ``fusion.multipath_sigma_m`` and ``multipath_tau_s`` (when over
   ``MIN_CORRELATED_M``). The white part is printed, not written: ``range_sigma_m`` also
   sets the update's gate and robust scales, and the white σ alone in it measured worse
   (docs/ekf.md §4).
5. **The NLOS tail**: the standardised residuals fitted by maximum likelihood as a Gaussian
   core with an exponential tail on each side; where the long tail's density overtakes the
   core's, a longer range is likelier NLOS than noise. That length is written as
   ``fusion.nlos_onset_m``: the robust update's long-side scale (docs/ekf.md §5, weights);
   not when the tail is too thin to say (under 1 % of the ranges, or overtaking only
   beyond 4 σ: the default stays). The short side's tail is no NLOS (a delay cannot be
   negative) and is not used.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from drivers.frames import Frame, UwbRanges
from uwbd.config.overrides import write_toml
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.models.range_model import (
    MAX_DEGREE,
    MIN_LOG_DISTANCE_M,
    basis,
    n_coefficients,
)
from uwbd.tools.evaluate import truth_spikes
from uwbd.tools.range_noise import TAIL_SIGMA, NoiseShape, noise_shape, robust_sigma

MAX_TRUTH_GAP_NS = 50_000_000
MAX_SPIKE_RATE_RPS = 20.0
CAUCHY_C = 2.385  # the Cauchy loss's scale in σ: 95 % efficiency at Gaussian noise
BLOCK_S = 10.0
HOLDOUT_FRACTION = 0.3
MIN_RANGES = 500
MIN_SPAN_S = 30.0
MIN_BIAS_RANGES = 50  # an anchor's held-out ranges that say what bias its calibration leaves
MIN_CORRELATED_M = 0.01  # a correlated part smaller than this is not worth the states
MIN_DISTANCE_SIGMAS = 3.0  # the distance term is written when this many σ from zero


class RangeCalibrationError(ValueError):
    """The log cannot calibrate a range model (no truth, too few ranges, ...)."""


@dataclass
class RangeSamples:
    """Each range with the truth at its time."""

    t_ns: npt.NDArray[np.int64]
    anchor: npt.NDArray[np.int64]
    range_m: Array
    distance_m: Array  # |p_antenna − a| by the truth
    u_tag: Array  # (n, 3) the anchor -> tag ray in the tag's axes
    u_anchor: Array  # (n, 3) the same ray in its anchor's axes (NaN rows: no orientation)

    @property
    def residual_m(self) -> Array:
        return self.range_m - self.distance_m

    def take(self, keep: npt.NDArray[np.bool_]) -> RangeSamples:
        return RangeSamples(self.t_ns[keep], self.anchor[keep], self.range_m[keep],
                            self.distance_m[keep], self.u_tag[keep], self.u_anchor[keep])


def _attitude_spikes(rotation: Array, t_ns: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
    """Lone attitude samples turned away from both neighbours faster than
    ``MAX_SPIKE_RATE_RPS``."""
    rel = np.einsum("nji,njk->nik", rotation[:-1], rotation[1:])  # R_kᵀ R_k+1
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    rate = np.arccos(cos) / np.maximum(np.diff(t_ns) / 1e9, 1e-6)
    fast = rate > MAX_SPIKE_RATE_RPS
    spikes = np.zeros(len(t_ns), dtype=bool)
    spikes[1:-1] = fast[:-1] & fast[1:]
    return spikes


def range_samples(frames: Iterable[Frame], anchors_m: Mapping[int, Sequence[float]],
                  truth_t_ns: npt.NDArray[np.int64], truth_p_m: Array, truth_rotation: Array,
                  lever_arm_m: Sequence[float], tag_mounting: Sequence[Sequence[float]],
                  anchor_axes: Mapping[int, npt.ArrayLike] | None = None
                  ) -> RangeSamples:
    """Every tag range of ``frames`` whose anchor is known (configured, or sent with it)
    against the truth at its time; the rays in the anchors' axes where ``anchor_axes``
    (anchor axes -> navigation frame) gives them."""
    good = ~(truth_spikes(truth_t_ns, truth_p_m) | _attitude_spikes(truth_rotation, truth_t_ns))
    tt, tp, tr = truth_t_ns[good], truth_p_m[good], truth_rotation[good]
    if len(tt) < 2:
        raise RangeCalibrationError("no ground truth (/truth) to calibrate against")
    t, ids, r, a = [], [], [], []
    for f in frames:
        if not isinstance(f, UwbRanges):
            continue
        for x in f.ranges:
            pos = anchors_m.get(x.anchor_id, x.anchor_position_m)
            if pos is not None and math.isfinite(x.range_m):
                t.append(f.t_ns)
                ids.append(x.anchor_id)
                r.append(x.range_m)
                a.append(pos)
    t_ns = np.array(t, dtype=np.int64)
    k = np.searchsorted(tt, t_ns)
    inside = (k > 0) & (k < len(tt))
    k = np.clip(k, 1, len(tt) - 1)
    inside &= (tt[k] - tt[k - 1]) <= MAX_TRUTH_GAP_NS
    t_ns, k = t_ns[inside], k[inside]
    anchor = np.array(ids, dtype=np.int64)[inside]
    range_m = np.array(r, dtype=float)[inside]
    anchors = np.array(a, dtype=float).reshape(-1, 3)[inside]
    frac = ((t_ns - tt[k - 1]) / (tt[k] - tt[k - 1]))[:, None]
    p = tp[k - 1] * (1 - frac) + tp[k] * frac
    unique_t, first = np.unique(tt, return_index=True)
    slerp = Slerp(unique_t.astype(float), Rotation.from_matrix(tr[first]))
    R = slerp(t_ns.astype(float)).as_matrix().reshape(-1, 3, 3)
    d = p + R @ np.asarray(lever_arm_m, dtype=float) - anchors
    dist = np.linalg.norm(d, axis=1)
    # u = C_tbᵀ Rᵀ d / |d|
    u = np.einsum("ji,nkj,nk->ni", np.asarray(tag_mounting, dtype=float), R, d)
    u /= np.maximum(np.linalg.norm(u, axis=1), 1e-9)[:, None]
    u_anchor = np.full((len(t_ns), 3), np.nan)
    for axes_of, rows in (anchor_axes or {}).items():
        mine = anchor == axes_of
        u_anchor[mine] = d[mine] @ np.asarray(rows, dtype=float) / dist[mine, None]  # Cᵀ d
    return RangeSamples(t_ns, anchor, range_m, dist, u, u_anchor)


def _design(s: RangeSamples, degree: int, anchor_ids: Sequence[int], distance: bool,
            anchor_degree: int = 0) -> Array:
    """Columns: each anchor's offset, the tag's harmonics, the anchors' (``anchor_degree``;
    every sample's anchor oriented) and (``distance``) ln(d / 1 m)."""
    offsets = (s.anchor[:, None] == np.asarray(anchor_ids)[None, :]).astype(float)
    log_d = np.log(np.maximum(s.distance_m, MIN_LOG_DISTANCE_M))[:, None]
    return np.hstack([offsets, basis(s.u_tag, degree), basis(s.u_anchor, anchor_degree)]
                     + ([log_d] if distance else []))


def _irls(A: Array, e: Array, iterations: int = 30) -> Array:
    """Cauchy-loss fit of ``e ≈ A x`` (iteratively reweighted least squares)."""
    x: Array = np.linalg.lstsq(A, e, rcond=None)[0].astype(float)
    for _ in range(iterations):
        res = e - A @ x
        scale = max(CAUCHY_C * robust_sigma(res), 0.005)
        w = 1.0 / (1.0 + (res / scale) ** 2)
        sw = np.sqrt(w)
        new: Array = np.linalg.lstsq(A * sw[:, None], e * sw, rcond=None)[0].astype(float)
        if np.max(np.abs(new - x)) < 1e-6:
            return new
        x = new
    return x


@dataclass
class ModelFit:
    degree: int
    anchor_ids: tuple[int, ...]
    offsets_m: Array
    coefficients_m: Array
    coefficient_sigma_m: Array
    log_distance_m: float | None = None  # k of k ln(d / 1 m); None: not fitted
    log_distance_sigma_m: float = math.nan
    anchor_degree: int = 0  # the anchors' direction term
    anchor_coefficients_m: Array = dataclasses.field(default_factory=lambda: np.zeros(0))
    anchor_coefficient_sigma_m: Array = dataclasses.field(default_factory=lambda: np.zeros(0))

    def delay_m(self, s: RangeSamples) -> Array:
        """The model's delay of each sample (offsets, direction and distance terms)."""
        distance = self.log_distance_m is not None
        x = np.concatenate([self.offsets_m, self.coefficients_m, self.anchor_coefficients_m]
                           + ([[self.log_distance_m]] if distance else []))
        return np.asarray(_design(s, self.degree, self.anchor_ids, distance,
                                  self.anchor_degree) @ x, dtype=float)


def fit(s: RangeSamples, degree: int, distance: bool, jackknife: bool = True,
        anchor_degree: int = 0) -> ModelFit:
    """The offsets, the tag's term of ``degree``, the anchors' of ``anchor_degree`` and
    (``distance``) the distance term."""
    ids = tuple(int(a) for a in np.unique(s.anchor))
    e = s.residual_m
    A = _design(s, degree, ids, distance, anchor_degree)
    x = _irls(A, e)
    n_off, n_tag, n_anchor = len(ids), n_coefficients(degree), n_coefficients(anchor_degree)
    sigma = np.full(A.shape[1] - n_off, math.nan)
    if jackknife and A.shape[1] > n_off:
        block = (s.t_ns - s.t_ns[0]) // int(BLOCK_S * 1e9)
        blocks = np.unique(block)
        if len(blocks) >= 3:
            xs = np.array([_irls(A[block != b], e[block != b], 10)[n_off:] for b in blocks])
            m = len(blocks)
            sigma = np.sqrt((m - 1) / m * ((xs - xs.mean(axis=0)) ** 2).sum(axis=0))
    tag, anchor = slice(0, n_tag), slice(n_tag, n_tag + n_anchor)
    coefficients = x[n_off:]
    return ModelFit(degree, ids, x[:n_off], coefficients[tag], sigma[tag],
                    float(x[-1]) if distance else None,
                    float(sigma[-1]) if distance else math.nan, anchor_degree,
                    coefficients[anchor], sigma[anchor])


@dataclass
class RangeCalibration:
    fit: ModelFit
    noise: NoiseShape
    n_ranges: int
    span_s: float
    anchors: int
    # degree -> held-out σ with the model of that degree, without and with the distance term
    held_out: dict[int, tuple[float, float]]
    before_sigma_m: float  # the robust σ of the ranges with the offsets only
    distance_fit: tuple[float, float]  # k and its σ as fitted, written or not
    # held-out σ of the fitted model without, then with, the anchors' term (None: not asked)
    anchor_held_out: tuple[float, ...] | None = None
    # what the model leaves of a range's bias: the largest anchor's mean held-out residual
    bias_bound_m: float | None = None

    def keys(self, anchor_delays: bool = True) -> dict[str, dict[str, object]]:
        """The config keys: ``[range_model]`` (the tag's term, the distance term, 0 where
        not fitted; with ``anchor_delays`` each anchor's delay too); the noise's
        ``fusion.nlos_onset_m``, ``multipath_sigma_m`` and ``multipath_tau_s`` (steps 4 and
        5, each where measured); and ``fusion.range_bias_states``: false with the delays,
        which are known (on the recordings measured estimating them again costs accuracy,
        docs/ekf.md §4, range model), true without them (the robot's anchors are other
        units: the states estimate their delays)."""
        f = self.fit
        model: dict[str, object] = {"tag_degree": f.degree, "tag_coefficients_m": [
            round(float(c), 5) for c in f.coefficients_m]}
        # always written: 0 clears a term that an earlier calibration left in the config
        model["log_distance_m"] = round(f.log_distance_m or 0.0, 4)
        model["anchor_degree"] = f.anchor_degree
        model["anchor_coefficients_m"] = [round(float(c), 5) for c in f.anchor_coefficients_m]
        n = self.noise
        fusion: dict[str, object] = {}
        if n.nlos.onset_m is not None:
            fusion["nlos_onset_m"] = round(n.nlos.onset_m, 3)
        if n.fast_sigma_m >= MIN_CORRELATED_M:
            fusion["multipath_sigma_m"] = round(n.fast_sigma_m, 3)
            fusion["multipath_tau_s"] = round(n.fast_tau_s, 2)
        if anchor_delays:
            model["anchor_delays_m"] = {str(a): round(float(o), 4)
                                        for a, o in zip(f.anchor_ids, f.offsets_m, strict=True)}
        # the delays known, or the states to estimate the robot's own (other units')
        fusion["range_bias_states"] = not anchor_delays
        if self.bias_bound_m is not None:  # the protection levels' bias bound, calibrated
            fusion["range_bias_bound_m"] = self.bias_bound_m
        return {"range_model": model, **({"fusion": fusion} if fusion else {})}

    def overrides(self, source: str, anchor_delays: bool = True) -> list[str]:
        """The keys as ``--set`` items."""
        items = [f"range_model.calibrated_from={_toml(source)}"]
        for section, table in self.keys(anchor_delays).items():
            items += [f"{section}.{k}={_toml(v)}" for k, v in table.items()]
        return items

    def snippet(self, source: str, anchor_delays: bool = True) -> str:
        """The keys as TOML, for a config."""
        keys = self.keys(anchor_delays)
        keys["range_model"] = {**keys["range_model"], "calibrated_from": source}
        distance = self.fit.log_distance_m is not None
        return (f"# uwbd calibrate-ranges {source}: the tag antenna's direction term"
                + (", the distance term" if distance else "")
                + (" and the anchors' antenna delays" if anchor_delays else "")
                + "\n# merge these sections' keys into the config\n" + write_toml(keys))

    def summary(self, where: str, tag_mounting_said: str) -> str:
        f, n = self.fit, self.noise
        lines = [f"{where}: {self.n_ranges} ranges to {self.anchors} anchors over "
                 f"{self.span_s:.0f} s against the truth"]
        lines.append("held out (fitted on the first 70 %, scored on the last 30 %), robust σ "
                     "of the ranges, without -> with the distance term:")
        plain = self.held_out[0][0]
        for degree, (without, distanced) in sorted(self.held_out.items()):
            lines.append(f"  {f'degree {degree}' if degree else 'offsets only'}: "
                         + " -> ".join(f"{v:.4f} m ({100 * (v / plain - 1):+.0f} %)"
                                       for v in (without, distanced))
                         + ("   <- fitted" if degree == f.degree else ""))
        if f.degree:
            lines.append(f"tag term, degree {f.degree} ({tag_mounting_said}), coefficients "
                         "± σ (10 s block jackknife):")
            lines += _coefficient_rows(f.coefficients_m, f.coefficient_sigma_m, f.degree)
            c = f.coefficients_m
            lines.append(f"  degree 1 as a phase centre (tag axes): ({math.sqrt(3) * c[2]:+.3f}, "
                         f"{math.sqrt(3) * c[0]:+.3f}, {math.sqrt(3) * c[1]:+.3f}) m")
        if f.anchor_degree and self.anchor_held_out is not None:
            without, with_term = self.anchor_held_out
            lines.append(f"anchors' term, degree {f.anchor_degree} (each anchor's axes), "
                         "coefficients ± σ; held out "
                         f"{without:.4f} m without it -> {with_term:.4f} m with it "
                         f"({100 * (with_term / without - 1):+.0f} %):")
            lines += _coefficient_rows(f.anchor_coefficients_m, f.anchor_coefficient_sigma_m,
                                       f.anchor_degree)
        distance = f.log_distance_m
        fitted, fitted_sigma = self.distance_fit
        lines.append(f"distance term k ln(d / 1 m): k {fitted:+.4f} ± {fitted_sigma:.4f} m " + (
            "(range_model.log_distance_m)" if distance is not None else
            "not written (0: it does not lower the held-out spread, or is not "
            f"{MIN_DISTANCE_SIGMAS:g} σ above zero; a delay that shrinks with distance is no "
            "DW1000's: is the truth's scale the anchors'?)"))
        lines.append("anchor antenna delays (each unit's own; with the tag's delay, common to "
                     "all" + (", at 1 m" if distance is not None else "") + "): " + ", ".join(
                         f"{a} {o:+.3f}" for a, o in zip(f.anchor_ids, f.offsets_m,
                                                         strict=True)) + " m")
        lines.append(f"robust σ of the ranges: {self.before_sigma_m:.4f} m with the offsets "
                     f"only, {n.core_sigma_m:.4f} m with the model")
        lines.append(f"noise left: robust σ {n.core_sigma_m:.4f} m; beyond {TAIL_SIGMA:g} σ "
                     f"{100 * n.long_fraction:.1f} % long, {100 * n.short_fraction:.1f} % short")
        lines.append(f"  white {n.white_sigma_m:.4f} m, correlated {n.fast_sigma_m:.4f} m over "
                     f"{n.fast_tau_s:.2f} s" + (
                         " (fusion.multipath_sigma_m, multipath_tau_s)"
                         if n.fast_sigma_m >= MIN_CORRELATED_M else " (too small to write)")
                     + f", slow {n.slow_sigma_m:.4f} m over {n.slow_tau_s:.0f} s")
        tail = n.nlos
        lines.append(f"  NLOS tail: {100 * tail.fraction:.1f} % of the ranges, exponential over "
                     f"{tail.scale_m:.3f} m; " + (
                         f"a range {tail.onset_m:.3f} m longer than predicted is likelier NLOS "
                         "than noise (fusion.nlos_onset_m)" if tail.onset_m is not None else
                         "nowhere likelier than noise: fusion.nlos_onset_m left to its default"))
        if self.bias_bound_m is not None:
            lines.append(f"bias left: each anchor's mean held-out residual {self.bias_bound_m:.2f} "
                         "m at most (fusion.range_bias_bound_m: the protection levels' bound)")
        return "\n".join(lines)


def _coefficient_rows(c: Array, sigma: Array, degree: int) -> list[str]:
    """A direction term's coefficients ± σ, a line per degree."""
    rows, k = [], 0
    for lv in range(1, degree + 1):
        rows.append("  " + "   ".join(f"c{lv},{m:+d} {c[k + m + lv]:+.4f} ± "
                                      f"{sigma[k + m + lv]:.4f}" for m in range(-lv, lv + 1)))
        k += 2 * lv + 1
    return rows


def _toml(v: object) -> str:
    return write_toml({"t": {"v": v}}).split(" = ", 1)[1].strip()


def calibrate(s: RangeSamples, degree: int, oriented: bool = True,
              anchor_degree: int = 0) -> RangeCalibration:
    """The model of ``degree`` (the anchors' term of ``anchor_degree``) and the noise, with
    every degree's held-out check. ``oriented``: the truth gives the tag's attitude (not the
    identity throughout)."""
    if not 0 <= degree <= MAX_DEGREE or not 0 <= anchor_degree <= MAX_DEGREE:
        raise RangeCalibrationError(f"degree {degree}, anchor degree {anchor_degree}: "
                                    f"expected 0..{MAX_DEGREE}")
    blind = sorted({int(a) for a in s.anchor[np.isnan(s.u_anchor[:, 0])]})
    if anchor_degree and blind:
        raise RangeCalibrationError(
            f"anchor(s) {', '.join(map(str, blind))} have no orientation in the config: the "
            "anchors' term needs each one's ([anchors] N = { position_m = [x, y, z], "
            "orientation_xyzw = [qx, qy, qz, qw] }; `uwbd import inrol` writes them)")
    span_s = float(s.t_ns[-1] - s.t_ns[0]) / 1e9 if len(s.t_ns) else 0.0
    if len(s.t_ns) < MIN_RANGES or span_s < MIN_SPAN_S:
        raise RangeCalibrationError(
            f"{len(s.t_ns)} ranges with truth over {span_s:.0f} s: a calibration needs "
            f"{MIN_RANGES} at least, over {MIN_SPAN_S:g} s (record about 90 s, the tag turned "
            "through every heading)")
    if degree > 0 and not oriented:
        raise RangeCalibrationError(
            "the ground truth has no orientation (every pose's attitude is the identity): the "
            "tag's direction term needs its attitude; --degree 0 fits the anchors' delays "
            "alone")
    cut = s.t_ns[0] + int((1 - HOLDOUT_FRACTION) * span_s * 1e9)
    train, test = s.take(s.t_ns < cut), s.take(s.t_ns >= cut)
    train = train.take(np.isin(train.anchor, np.unique(test.anchor)))
    test = test.take(np.isin(test.anchor, np.unique(train.anchor)))
    def held_out_sigma(d: int, distance: bool) -> float:
        return robust_sigma(test.residual_m - fit(train, d, distance, False).delay_m(test))

    held_out = {d: (held_out_sigma(d, False), held_out_sigma(d, True))
                for d in range(MAX_DEGREE + 1)}
    plain, distanced = held_out[degree]
    model = fit(s, degree, distance=True, anchor_degree=anchor_degree)
    k, k_sigma = model.log_distance_m or 0.0, model.log_distance_sigma_m
    distance = (k, k_sigma)
    with_distance = distanced < plain and k >= MIN_DISTANCE_SIGMAS * k_sigma
    if not with_distance:
        model = fit(s, degree, distance=False, anchor_degree=anchor_degree)
    anchor_held_out = None
    if anchor_degree:  # the fitted model held out without, then with, the anchors' term
        anchor_held_out = tuple(
            robust_sigma(test.residual_m - fit(train, degree, with_distance, False, a)
                         .delay_m(test)) for a in (0, anchor_degree))
    before = fit(s, 0, distance=False, jackknife=False)
    return RangeCalibration(model, noise_shape(s.t_ns, s.anchor, s.residual_m - model.delay_m(s)),
                            len(s.t_ns), span_s, len(model.anchor_ids), held_out,
                            robust_sigma(s.residual_m - before.delay_m(s)), distance,
                            anchor_held_out, bias_bound(test, test.residual_m - fit(
                                train, degree, with_distance, False, anchor_degree)
                                .delay_m(test)))


def bias_bound(s: RangeSamples, residual_m: Array) -> float | None:
    """The bias a calibrated range keeps, for the protection levels
    (``fusion.range_bias_bound_m``): the largest of the anchors' mean held-out residuals
    (each over ``MIN_BIAS_RANGES`` ranges at least), up to the next centimetre, 1 cm at
    least; None when no anchor has enough."""
    means = [abs(float(np.mean(residual_m[s.anchor == a]))) for a in np.unique(s.anchor)
             if int(np.sum(s.anchor == a)) >= MIN_BIAS_RANGES]
    if not means:
        return None
    return max(math.ceil(max(means) * 100) / 100, 0.01)
