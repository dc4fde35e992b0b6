"""Six-position IMU calibration (``uwbd calibrate-imu``): the accelerometer's scale and offset
per axis and the gyro's offset, from a log of the IMU held still with each axis up and then
down, a few seconds each, in any order.

1. **Static segments**: the samples whose 0.5 s window around them is still, the spread of
   every accelerometer and gyro axis under a threshold (4 times the quietest windows' spread,
   within fixed bounds), runs of them cut 0.2 s at each end and kept from ``min_static_s``.
2. **Orientations**: each segment's mean specific force names the axis that pointed up and
   its sign (``"+x"``: x up); a mean more than 20° off every axis, or not near ``g`` in size,
   is left out.
3. **Accelerometer**, model ``a_meas = scale · a_true + offset`` per axis (``a_true =
   (a_meas − offset) / scale``, what :mod:`uwbd.fusion.checks.intrinsics` applies), the thesis's
   pair formula ``offset = (a⁺ + a⁻) / 2``, ``scale = (a⁺ − a⁻) / (2 g)``, then refined by the
   constraint that every corrected static mean has the size ``g`` (Gauss–Newton on the six
   or more segments, whole vectors): the pair formula alone reads a hold tipped by θ as a
   scale low by θ²/2 (0.06 % at 2°), the refinement does not.
4. **Gyro**: the offset is the mean rate over every static sample (opposite orientations
   cancel the Earth's rate and a g-sensitive offset).

Each value comes with its standard uncertainty, propagated from the scatter of the segments'
samples: a segment mean's standard error is the larger of ``std/√n`` and the scatter of its
ten block means (samples are not quite independent); the gyro offset's, the larger of that
and the scatter between the segments.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.emulator import ENCODERS
from drivers.frames import ImuSample
from uwbd import config as cfgmod
from uwbd.config.overrides import write_toml
from uwbd.config.schema import INTRINSIC_BOUNDS
from uwbd.fusion.core.noise import GRAVITY_MPS2
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.settings import Z_DOWN
from uwbd.logs.mcaplog import LogWriter, SourceInfo
from uwbd.tools.simulator import DEFAULT_ANCHORS_M
from uwbd.tools.six_position import SixPositionCapture

ORIENTATIONS = ("+x", "-x", "+y", "-y", "+z", "-z")
SAID = {o: f"{o[1]} {'up' if o[0] == '+' else 'down'}" for o in ORIENTATIONS}
WINDOW_S = 0.5  # the stillness test's window
EDGE_S = 0.2  # cut from each end of a still run: the hand letting go, settling
MIN_STATIC_S = 1.5
MAX_OFF_AXIS_DEG = 20.0
ACC_STD_BOUNDS_MPS2 = (0.01, 0.3)  # the stillness thresholds: 4x the quietest, within these
GYRO_STD_BOUNDS_RPS = (0.002, 0.05)
BLOCKS = 10
DIGITS = {"acc_scale": 6, "acc_offset_mps2": 5, "gyro_offset_rps": 6}  # as written


class CalibrationError(ValueError):
    """The log cannot give a calibration: one line saying why."""


@dataclass(frozen=True)
class Segment:
    """One static run: its orientation (``None``: not along an axis), time span, samples,
    means and their standard errors (sensor axes)."""

    orientation: str | None
    start_ns: int
    end_ns: int
    n: int
    acc_mean: Array
    acc_sem: Array
    gyro_mean: Array
    gyro_sem: Array
    off_axis_deg: float

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9


@dataclass(frozen=True)
class Calibration:
    """The result: values and standard uncertainties per sensor axis, the ``g`` used, and
    the thesis's pair formula's values for comparison."""

    acc_scale: Array
    acc_scale_sigma: Array
    acc_offset_mps2: Array
    acc_offset_sigma_mps2: Array
    gyro_offset_rps: Array
    gyro_offset_sigma_rps: Array
    gravity_mps2: float
    method: str  # "fit" (refined) or "pairs" (the refinement did not converge)
    pairs_scale: Array
    pairs_offset_mps2: Array
    segments: tuple[Segment, ...]
    left_out: tuple[Segment, ...] = field(default=())  # static, but not along an axis

    def keys(self) -> dict[str, Any]:
        """The ``[imu]`` keys to set, rounded far below their uncertainty."""
        return {"acc_scale": _rounded(self.acc_scale, DIGITS["acc_scale"]),
                "acc_offset_mps2": _rounded(self.acc_offset_mps2, DIGITS["acc_offset_mps2"]),
                "gyro_offset_rps": _rounded(self.gyro_offset_rps, DIGITS["gyro_offset_rps"]),
                "gravity_mps2": float(self.gravity_mps2)}

    def overrides(self) -> list[str]:
        """The keys as ``--set`` items (``imu.acc_scale=[...]``)."""
        return [f"imu.{k}={_toml_value(v)}" for k, v in self.keys().items()]

    def snippet(self, source: str) -> str:
        """An ``[imu]`` table with the keys, for a config's ``[imu]`` section."""
        return (f"# uwbd calibrate-imu {source}: a_true = (a_meas - acc_offset_mps2) / "
                "acc_scale per sensor axis\n# merge these keys into the config's [imu] "
                "section\n" + write_toml({"imu": self.keys()}))

    def problems(self) -> list[str]:
        """Values outside what the config accepts (``imu.acc_scale[1] = 1.5: ...``)."""
        out = []
        for key, bounds in INTRINSIC_BOUNDS.items():
            for k, v in enumerate(self.keys()[key]):
                problem = bounds.problem(v)
                if problem is not None:
                    out.append(f"imu.{key}[{k}] {problem}")
        return out

    def summary(self, where: str) -> str:
        """What was found, for a person: segments, values ± uncertainty, the pair formula."""
        rate = sum(s.n for s in self.segments) / max(sum(s.duration_s for s in self.segments),
                                                      1e-9)
        held = ", ".join(f"{s.orientation} {s.duration_s:.1f} s ({s.off_axis_deg:.1f}° off)"
                         for s in sorted(self.segments,
                                         key=lambda s: ORIENTATIONS.index(s.orientation or "")))
        lines = [f"{where}: {len(self.segments)} static segments at {rate:.0f} Hz: {held}"]
        for s in self.left_out:
            lines.append(f"  left out: still for {s.duration_s:.1f} s but {s.off_axis_deg:.0f}° "
                         "off every axis")
        lines.append(f"accelerometer, a_true = (a_meas - acc_offset_mps2) / acc_scale, g = "
                     f"{self.gravity_mps2:g} m/s²"
                     + (" (the pair formula: the refinement did not converge)"
                        if self.method == "pairs" else "") + ":")
        for k, axis in enumerate("xyz"):
            lines.append(f"  {axis}: acc_scale {self.acc_scale[k]:.6f} ± "
                         f"{self.acc_scale_sigma[k]:.6f}   acc_offset_mps2 "
                         f"{self.acc_offset_mps2[k]:+.5f} ± {self.acc_offset_sigma_mps2[k]:.5f}")
        lines.append("gyro_offset_rps: " + ", ".join(
            f"{axis} {self.gyro_offset_rps[k]:+.6f} ± {self.gyro_offset_sigma_rps[k]:.6f}"
            for k, axis in enumerate("xyz")))
        if self.method == "fit":
            ds = float(np.abs(self.pairs_scale - self.acc_scale).max())
            do = float(np.abs(self.pairs_offset_mps2 - self.acc_offset_mps2).max())
            lines.append(f"(the ± pair formula alone differs by up to {ds:.6f} in scale and "
                         f"{do:.5f} m/s² in offset: the tilt of the holds)")
        return "\n".join(lines)


def _rounded(v: Array, digits: int) -> list[float]:
    return [round(float(x), digits) + 0.0 for x in v]  # + 0.0: no -0.0


def _toml_value(v: Any) -> str:
    return "[" + ", ".join(repr(float(x)) for x in v) + "]" if isinstance(v, list) else repr(v)


# -- static segments ------------------------------------------------------------------------
def _rolling_std(x: Array, w: int) -> Array:
    """The std of each column over the ``w`` samples centred on each sample (NaN where the
    window does not fit)."""
    x = x - np.median(x, axis=0)  # small numbers: the sums lose nothing
    c1 = np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros(x.shape[1]), np.cumsum(x * x, axis=0)])
    out = np.full(x.shape, np.nan)
    h = w // 2
    if len(x) >= w:
        s1, s2 = c1[w:] - c1[:-w], c2[w:] - c2[:-w]
        out[h:h + len(s1)] = np.sqrt(np.maximum(s2 / w - (s1 / w) ** 2, 0.0))
    return out


def _sem(x: Array) -> Array:
    """Standard error of the column means: the larger of std/√n and the scatter of
    ``BLOCKS`` block means."""
    n = len(x)
    white: Array = x.std(axis=0, ddof=1) / math.sqrt(n)
    if n < 4 * BLOCKS:
        return white
    blocks = np.array([b.mean(axis=0) for b in np.array_split(x, BLOCKS)])
    sem: Array = np.maximum(white, blocks.std(axis=0, ddof=1) / math.sqrt(BLOCKS))
    return sem


def static_segments(imu: Sequence[ImuSample], gravity_mps2: float = GRAVITY_MPS2,
                    min_static_s: float = MIN_STATIC_S) -> list[Segment]:
    """The still runs of ``imu`` (time-ordered), each with its orientation (module doc)."""
    if len(imu) < 10:
        return []
    t = np.array([s.t_ns for s in imu], dtype=np.int64)
    acc = np.array([s.acc_mps2 for s in imu], dtype=float)
    gyro = np.array([s.gyro_rps for s in imu], dtype=float)
    finite = np.isfinite(acc).all(axis=1) & np.isfinite(gyro).all(axis=1)
    t, acc, gyro = t[finite], acc[finite], gyro[finite]
    if len(t) < 10:
        return []
    rate = 1e9 / float(np.median(np.diff(t))) if np.median(np.diff(t)) > 0 else 100.0
    w = max(5, round(WINDOW_S * rate))
    a_std = np.linalg.norm(_rolling_std(acc, w), axis=1)
    g_std = np.linalg.norm(_rolling_std(gyro, w), axis=1)
    fits = np.isfinite(a_std)
    if not fits.any():
        return []
    a_thr = float(np.clip(4 * np.percentile(a_std[fits], 5), *ACC_STD_BOUNDS_MPS2))
    g_thr = float(np.clip(4 * np.percentile(g_std[fits], 5), *GYRO_STD_BOUNDS_RPS))
    still = fits & (a_std < a_thr) & (g_std < g_thr)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    out = []
    for i0, i1 in zip(edges[::2], edges[1::2], strict=True):
        keep = (t[i0:i1] >= t[i0] + EDGE_S * 1e9) & (t[i0:i1] <= t[i1 - 1] - EDGE_S * 1e9)
        idx = np.arange(i0, i1)[keep]
        if len(idx) < 10 or (t[idx[-1]] - t[idx[0]]) / 1e9 < min_static_s:
            continue
        a, g = acc[idx], gyro[idx]
        m = a.mean(axis=0)
        k = int(np.argmax(np.abs(m)))
        norm = float(np.linalg.norm(m))
        off = math.degrees(math.acos(min(abs(m[k]) / norm, 1.0))) if norm > 0 else 90.0
        along = off <= MAX_OFF_AXIS_DEG and 0.7 * gravity_mps2 <= norm <= 1.3 * gravity_mps2
        out.append(Segment(f"{'+' if m[k] > 0 else '-'}{'xyz'[k]}" if along else None,
                           int(t[idx[0]]), int(t[idx[-1]]), len(idx), m, _sem(a),
                           g.mean(axis=0), _sem(g), off))
    return out


# -- the solution ---------------------------------------------------------------------------
def calibrate(imu: Sequence[ImuSample], gravity_mps2: float = GRAVITY_MPS2,
              min_static_s: float = MIN_STATIC_S) -> Calibration:
    """The intrinsics from a six-position capture (module doc); :class:`CalibrationError`
    when the six orientations are not all there."""
    found = static_segments(imu, gravity_mps2, min_static_s)
    segments = [s for s in found if s.orientation is not None]
    left_out = tuple(s for s in found if s.orientation is None)
    have = {s.orientation for s in segments}
    missing = [o for o in ORIENTATIONS if o not in have]
    if missing:
        got = ", ".join(SAID[o] for o in ORIENTATIONS if o in have) or "none"
        extra = (f"; {len(left_out)} still segment(s) off every axis by more than "
                 f"{MAX_OFF_AXIS_DEG:g}°" if left_out else "")
        raise CalibrationError(
            f"no static segment of {min_static_s:g} s or more with "
            f"{', '.join(SAID[o] + f' ({o})' for o in missing)}: "
            f"{6 - len(missing)} of the 6 orientations found ({got}){extra}; hold the IMU "
            "still with each axis up and then down in turn, a few seconds each")
    g = gravity_mps2
    plus = {o: _pooled([s for s in segments if s.orientation == o]) for o in ORIENTATIONS}
    scale, offset, s_sig, o_sig = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    for k, axis in enumerate("xyz"):
        (ap, sp), (am, sm) = plus["+" + axis], plus["-" + axis]
        offset[k] = (ap[k] + am[k]) / 2
        scale[k] = (ap[k] - am[k]) / (2 * g)
        o_sig[k] = math.hypot(sp[k], sm[k]) / 2
        s_sig[k] = math.hypot(sp[k], sm[k]) / (2 * g)
    method = "pairs"
    result = (scale.copy(), offset.copy(), s_sig, o_sig)
    fitted = _norm_fit(segments, g, scale, offset)
    if fitted is not None:
        result, method = fitted, "fit"
    gyro, gyro_sig = _gyro_offset(segments)
    return Calibration(result[0], result[2], result[1], result[3], gyro, gyro_sig, g, method,
                       scale, offset, tuple(segments), left_out)


def _pooled(segments: list[Segment]) -> tuple[Array, Array]:
    """The mean of one orientation's segments (weighted by their standard errors) and its
    standard error."""
    w = np.array([1.0 / np.maximum(s.acc_sem, 1e-12) ** 2 for s in segments])
    m = np.array([s.acc_mean for s in segments])
    return (w * m).sum(axis=0) / w.sum(axis=0), 1.0 / np.sqrt(w.sum(axis=0))


def _norm_fit(segments: list[Segment], g: float, scale: Array, offset: Array
              ) -> tuple[Array, Array, Array, Array] | None:
    """Scale and offset such that every corrected segment mean has the size ``g``, weighted
    by each residual's variance; ``None`` when it does not converge near the pair values."""
    m = np.array([s.acc_mean for s in segments])
    sem = np.array([s.acc_sem for s in segments])
    s_, o_ = scale.copy(), offset.copy()
    for _ in range(30):
        c = (m - o_) / s_  # corrected means
        norm = np.linalg.norm(c, axis=1)
        u = c / norm[:, None]
        r = norm - g
        J = np.hstack([-u / s_, -u * c / s_])  # d r / d (offset, scale)
        var = np.sum((u / s_) ** 2 * sem**2, axis=1)
        W = 1.0 / np.maximum(var, 1e-18)
        A = J.T @ (W[:, None] * J)
        try:
            step = np.linalg.solve(A, -J.T @ (W * r))
        except np.linalg.LinAlgError:
            return None
        o_, s_ = o_ + step[:3], s_ + step[3:]
        if not np.all(np.isfinite(step)) or np.any(s_ <= 0):
            return None
        if np.abs(step).max() < 1e-12:
            break
    else:
        return None
    try:
        cov = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return None
    dof = len(segments) - 6
    if dof > 0:  # more segments than unknowns: their scatter says how far to trust them
        cov *= max(1.0, float(np.sum(W * r**2)) / dof)
    if np.abs(s_ - scale).max() > 0.1 or np.abs(o_ - offset).max() > 1.0:
        return None  # far from the pair formula: something else is wrong; keep that
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return s_, o_, sig[3:], sig[:3]


def _gyro_offset(segments: list[Segment]) -> tuple[Array, Array]:
    """The mean rate over every static sample, and its standard error: the larger of the
    samples' and the scatter between the segments'."""
    n = np.array([s.n for s in segments], dtype=float)
    means = np.array([s.gyro_mean for s in segments])
    sems = np.array([s.gyro_sem for s in segments])
    mean = (n[:, None] * means).sum(axis=0) / n.sum()
    within = np.sqrt(((n[:, None] * sems) ** 2).sum(axis=0)) / n.sum()
    between = means.std(axis=0, ddof=1) / math.sqrt(len(segments))
    return mean, np.maximum(within, between)


# -- a simulated capture as a log ----------------------------------------------------------------
def write_capture(capture: SixPositionCapture, path: Path) -> None:
    """The capture as a log as ``uwbd run`` records one: the IMU's bytes (WitMotion) on
    ``/raw/imu``, a config with an IMU and a (silent) UWB source."""
    sources = (cfgmod.SourceConfig("imu", "wit", "simulated", 921600),
               cfgmod.SourceConfig("uwb", "nlink", "simulated", 921600))
    toml = cfgmod.to_toml(sources, dict(enumerate(DEFAULT_ANCHORS_M)), Z_DOWN, (0.0, 0.0, 0.1))
    encode = ENCODERS["wit"]
    with LogWriter(path, toml, tuple(SourceInfo(s.name, s.driver, s.port)
                                     for s in sources)) as log:
        next_flush = capture.imu[0].t_ns if capture.imu else 0
        for sample in capture.imu:
            log.raw("imu", sample.t_ns, encode(sample))
            if sample.t_ns >= next_flush:
                log.flush()
                next_flush += 1_000_000_000
