"""``uwbd report log.mcap``: every method on one recording, scored against its ground truth.

Methods: pure INS, UWB least squares, the same with the thesis's static-point filtering
(fixes averaged while at rest), the thesis's 4-state KF (dual-gain complementary attitude,
static points at rest) and its variant with the two gains swapped, the loose and tight
error-state filters with the log's own config, and the tight filter RTS-smoothed (what a
log allows offline); see :mod:`uwbd.tools.baselines`. Printed: position RMSE (XY, Z, 3D)
and position NEES/3 per method, the tight filter's mean NIS per accepted range, how often
the baselines' motion tests fired (the share of time at the attitude's turning or
accelerating gain, the share of fixes averaged at rest), and, where the truth has
motion-capture spikes, the same table without them; where the log has truth and ranges,
the ranges' residuals against it (robust σ, median per anchor), raw and with the config's
range model taken off. Written: ``trajectory.png`` (XY paths), ``error.png`` (horizontal
error over time) and ``ranges.png`` (the range residuals by anchor, by the ray's direction in
the tag's axes and by distance, raw and with the range model).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display needed
import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from uwbd.fusion.core.rotation import Array
from uwbd.fusion.settings import Mode
from uwbd.tools.baselines import Baseline, Kf4, StaticPoints, comparison_methods
from uwbd.tools.evaluate import (
    HEADER,
    Times,
    run_filter,
    run_method,
    run_smoother,
    score,
    truth_spikes,
)
from uwbd.tools.logtools import Recording
from uwbd.tools.range_calibration import RangeCalibrationError, RangeSamples, range_samples
from uwbd.tools.range_noise import robust_sigma

Track = tuple[Times, Array, Array | None]


def run_all(rec: Recording, progress: bool = False
            ) -> tuple[dict[str, Track], dict[str, float]]:
    """Positions (and covariances) of every method; consistency figures of the filters.
    ``progress``: a bar on stderr, one step per method."""
    cfg = rec.config.filter_config()
    tracks: dict[str, Track] = {}
    methods = comparison_methods(cfg)
    bar = tqdm(total=len(methods) + len(Mode) + 1, desc="report", unit="method",
               disable=not progress, leave=False)
    extra: dict[str, float] = {}
    for name, method in methods.items():
        bar.set_postfix_str(name)
        t, p = run_method(method, rec.frames)
        tracks[name] = (t, p, None)
        extra.update(_motion_shares(name, method, len(t)))
        bar.update()
    for mode in Mode:
        bar.set_postfix_str(f"{mode.value} ESKF")
        poses, reports, _ = run_filter(dataclasses.replace(cfg, mode=mode), rec.frames)
        tracks[f"{mode.value} ESKF"] = (
            np.array([q.t_ns for q in poses], dtype=np.int64),
            np.array([q.position_m for q in poses]).reshape(-1, 3),
            np.array([np.array(q.covariance).reshape(6, 6)[:3, :3] for q in poses]))
        nis = [r.nis for r in reports if r.accepted and r.kind in ("range", "position")]
        mean_nis = float(np.mean(nis)) if nis else math.nan  # nan: nothing was accepted
        extra[f"{mode.value} ESKF mean NIS (accepted UWB)"] = mean_nis
        bar.update()
    bar.set_postfix_str("RTS smoother")
    tracks["tight + RTS smoother"] = run_smoother(dataclasses.replace(cfg, mode=Mode.TIGHT),
                                                  rec.frames)
    bar.close()
    return tracks, extra


def _motion_shares(name: str, method: Baseline, n_positions: int) -> dict[str, float]:
    """How often a baseline's motion tests fired (nan: it never ran)."""
    if isinstance(method, Kf4):
        att = method.attitude
        total_s = att.moving_s + att.still_s
        return {f"{name}: share of time at the turning/accelerating gain":
                att.moving_s / total_s if total_s > 0 else math.nan}
    if isinstance(method, StaticPoints):
        return {f"{name}: share of fixes averaged at rest":
                method.rest_fixes / n_positions if n_positions else math.nan}
    return {}


def report(rec: Recording, out_dir: Path, skip_s: float = 0.0, progress: bool = False) -> str:
    """The text report; plots go to ``out_dir``."""
    tracks, extra = run_all(rec, progress)
    lines = []
    if len(rec.truth_t_ns) < 2:
        lines.append("no ground truth in this log: positions only, no accuracy")
    else:
        spikes = truth_spikes(rec.truth_t_ns, rec.truth_p_m)
        cases = [("all truth samples", np.ones(len(spikes), dtype=bool))]
        if spikes.any():
            cases.append((f"truth without its {int(spikes.sum())} motion-capture spike(s)",
                          ~spikes))
        for label, mask in cases:
            lines += [f"position error against {label}", HEADER]
            for name, (t, p, cov) in tracks.items():
                if len(t):
                    lines.append(score(t, p, rec.truth_t_ns[mask], rec.truth_p_m[mask], cov,
                                       skip_s).row(name))
            lines.append("")
    lines += [f"{k}: {v:.2f}" for k, v in extra.items()]
    out_dir.mkdir(parents=True, exist_ok=True)
    written = _plots(rec, tracks, out_dir)
    residuals = range_residuals(rec)
    if residuals is not None:
        lines += residuals.summary()
        written.append(residuals.plot(out_dir / "ranges.png"))
    else:
        (out_dir / "ranges.png").unlink(missing_ok=True)
    lines.append("plots: " + ", ".join(str(path) for path in written))
    return "\n".join(lines)


def _plots(rec: Recording, tracks: dict[str, Track], out_dir: Path) -> list[Path]:
    """The trajectory plot, and the error plot where the log has truth: the files written."""
    fig, ax = plt.subplots(figsize=(8, 7))
    if len(rec.truth_t_ns) >= 2:
        good = rec.truth_p_m[~truth_spikes(rec.truth_t_ns, rec.truth_p_m)]
        ax.plot(good[:, 0], good[:, 1], "k-", lw=2.5, label="truth (spikes removed)")
    for name, (_, p, _) in tracks.items():
        if len(p) and name != "pure INS":  # it leaves the room; its error plot shows it
            ax.plot(p[:, 0], p[:, 1], lw=1, label=name)
    anchors = np.array(list(rec.config.anchors_m.values())).reshape(-1, 3)
    ax.plot(anchors[:, 0], anchors[:, 1], "r^", label="anchors")
    ax.set(xlabel="east (m)", ylabel="north (m)", title="trajectory (ENU, top view)")
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    fig.savefig(out_dir / "trajectory.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    written = [out_dir / "trajectory.png"]
    if len(rec.truth_t_ns) < 2:
        (out_dir / "error.png").unlink(missing_ok=True)  # not an earlier run's, beside this one
        return written  # no truth, no error to plot
    fig, ax = plt.subplots(figsize=(10, 4))
    t0 = rec.truth_t_ns[0]
    for name, (t, p, _) in tracks.items():
        if not len(t):
            continue
        truth = np.column_stack([np.interp(t, rec.truth_t_ns, rec.truth_p_m[:, i])
                                 for i in range(2)])
        ax.plot((t - t0) / 1e9, np.linalg.norm(p[:, :2] - truth, axis=1), lw=0.8,
                label=name)
    ax.set_yscale("log")
    ax.set(xlabel="time (s)", ylabel="horizontal error (m)", title="error over time")
    ax.legend(fontsize=8)
    fig.savefig(out_dir / "error.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return [*written, out_dir / "error.png"]


@dataclasses.dataclass
class RangeResiduals:
    """Each range against the truth: raw (``r − |p_antenna − a|``), and with the config's
    range model taken off (the anchors' delays, the distance term and the tag's direction
    term)."""

    samples: RangeSamples
    raw_m: Array
    modelled_m: Array | None  # None: no [range_model] configured

    def summary(self) -> list[str]:
        s, raw = self.samples, self.raw_m
        line = (f"ranges against the truth ({len(raw)}): robust σ {robust_sigma(raw):.3f} m raw"
                + (f", {robust_sigma(self.modelled_m):.3f} m with the range model"
                   if self.modelled_m is not None else
                   " (no [range_model]: uwbd calibrate-ranges fits one)"))
        per = []
        for a in np.unique(s.anchor):
            mine = s.anchor == a
            per.append(f"{a} {np.median(raw[mine]):+.3f}"
                       + (f"/{np.median(self.modelled_m[mine]):+.3f}"
                          if self.modelled_m is not None else ""))
        return [line, "  median per anchor (raw" + ("/modelled" if self.modelled_m is not None
                                                      else "") + ", m): " + ", ".join(per)]

    def plot(self, path: Path) -> Path:
        s = self.samples
        cases = [("raw", self.raw_m)] + ([("range model taken off", self.modelled_m)]
                                          if self.modelled_m is not None else [])
        fig, axes = plt.subplots(1, 4, figsize=(20, 4.2))
        ids = np.unique(s.anchor)
        width = 0.8 / len(cases)
        for k, (label, e) in enumerate(cases):
            axes[0].boxplot([e[s.anchor == a] for a in ids], positions=np.arange(len(ids))
                            + (k - (len(cases) - 1) / 2) * width, widths=width * 0.9,
                            showfliers=False, patch_artist=True,
                            boxprops={"facecolor": f"C{k}", "alpha": 0.6})
            axes[0].plot([], [], color=f"C{k}", lw=6, alpha=0.6, label=label)
            far_m = max(float(np.max(s.distance_m)), 1.0)
            for ax, value, edges in (
                    (axes[1], np.degrees(np.arctan2(s.u_tag[:, 1], s.u_tag[:, 0])),
                     np.linspace(-180, 180, 37)),
                    (axes[2], np.degrees(np.arcsin(np.clip(s.u_tag[:, 2], -1, 1))),
                     np.linspace(-90, 90, 19)),
                    (axes[3], s.distance_m, np.linspace(0.0, far_m, 21))):
                where = np.digitize(value, edges) - 1
                mid = (edges[:-1] + edges[1:]) / 2
                med = np.array([np.median(e[where == i]) if (where == i).sum() >= 20
                                else np.nan for i in range(len(mid))])
                ax.plot(mid, med, "o-", color=f"C{k}", label=label)
        axes[0].set_xticks(np.arange(len(ids)), [str(a) for a in ids])
        axes[0].set(xlabel="anchor", ylabel="range residual (m)",
                    title="by anchor (boxes: quartiles, whiskers 1.5 IQR)")
        axes[1].set(xlabel="azimuth of the anchor→tag ray, tag axes (°)",
                    ylabel="median residual (m)", title="by direction: azimuth")
        axes[2].set(xlabel="elevation of the anchor→tag ray, tag axes (°)",
                    ylabel="median residual (m)", title="by direction: elevation")
        axes[3].set(xlabel="distance tag–anchor (m)", ylabel="median residual (m)",
                    title="by distance")
        for ax in axes:
            ax.axhline(0.0, color="k", lw=0.5)
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        return path


def range_residuals(rec: Recording) -> RangeResiduals | None:
    """The ranges against the truth, where the log has both (``None`` otherwise)."""
    c = rec.config
    model = c.range_model_settings()
    if len(rec.truth_t_ns) < 2:
        return None
    try:
        s = range_samples(rec.frames, c.anchors_m, rec.truth_t_ns, rec.truth_p_m,
                          rec.truth_rotation, c.lever_arm_m, model.tag_mounting,
                          c.anchor_axes)
    except RangeCalibrationError:
        return None
    if len(s.t_ns) < 20:
        return None
    raw = s.residual_m
    if not (model.enabled or model.anchor_delays_m or model.log_distance_m
            or model.anchor_degree):
        return RangeResiduals(s, raw, None)
    return RangeResiduals(s, raw, raw - model.delay_m(s.anchor, s.u_tag, s.distance_m,
                                                      s.u_anchor))
