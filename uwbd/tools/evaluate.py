"""Running a method over time-ordered frames and scoring it against ground truth."""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from drivers.frames import Frame, ImuSample, UwbRanges
from uwbd.fusion.core.layout import P_
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.smoother import smooth
from uwbd.fusion.filter import Filter
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import FusionReport, Pose


def merge(imu: Iterable[ImuSample], uwb: Iterable[UwbRanges]) -> Iterator[Frame]:
    """Both streams in timestamp order; at equal times the IMU sample comes first."""
    imu_items: Iterator[tuple[int, int, Frame]] = ((f.t_ns, 0, f) for f in imu)
    uwb_items: Iterator[tuple[int, int, Frame]] = ((f.t_ns, 1, f) for f in uwb)
    tagged = heapq.merge(imu_items, uwb_items, key=lambda x: (x[0], x[1]))
    return (f for _, _, f in tagged)


def run_filter(config: FilterConfig, frames: Iterable[Frame], record: bool = False,
               pose_period_ns: int | None = None,
               watch: Callable[[Filter], None] | None = None
               ) -> tuple[list[Pose], list[FusionReport], Filter]:
    """The filter over ``frames``; a pose after every UWB message, or with
    ``pose_period_ns`` as the daemon brings them out (:mod:`uwbd.service.pipeline`): after
    every epoch of several ranges, and from the IMU samples and single ranges once a period
    has passed (``record``: for smoothing; ``watch``: called with the filter after every
    UWB message)."""
    flt = Filter(config, record)
    poses: list[Pose] = []
    reports: list[FusionReport] = []
    last_ns = -(2**63)
    for frame in frames:
        if isinstance(frame, ImuSample):
            flt.predict(frame)
            if pose_period_ns is None or frame.t_ns - last_ns < pose_period_ns:
                continue
        else:
            reports += flt.update(frame)
            if watch is not None:
                watch(flt)
            if pose_period_ns is not None and isinstance(frame, UwbRanges) and \
                    len(frame.ranges) < 2 and frame.t_ns - last_ns < pose_period_ns:
                continue  # a single range: the next pose is due later
        pose = flt.pose()
        if pose is not None:
            poses.append(pose)
            last_ns = pose.t_ns
    reports += flt.flush()
    return poses, reports, flt


def run_smoother(config: FilterConfig, frames: Iterable[Frame]
                 ) -> tuple[npt.NDArray[np.int64], Array, Array]:
    """The filter over ``frames``, then RTS-smoothed: times, IMU positions and their
    covariances at every UWB epoch."""
    _, _, flt = run_filter(config, frames, record=True)
    assert flt.records is not None
    smoothed = smooth(flt.records)
    return (np.array([t for t, _, _ in smoothed], dtype=np.int64),
            np.array([x.p for _, x, _ in smoothed]).reshape(-1, 3),
            np.array([P[P_, P_] for _, _, P in smoothed]).reshape(-1, 3, 3))


@dataclass(frozen=True)
class Accuracy:
    n: int
    rmse_xy_m: float
    rmse_z_m: float
    rmse_3d_m: float
    nees_mean: float  # position NEES / 3: about 1 when consistent

    def row(self, name: str) -> str:
        return (f"{name:<22} {self.rmse_xy_m:8.3f} {self.rmse_z_m:8.3f} {self.rmse_3d_m:8.3f}"
                f" {self.nees_mean:9.2f} {self.n:7d}")


HEADER = f"{'method':<22} {'XY m':>8} {'Z m':>8} {'3D m':>8} {'NEES/3':>9} {'n':>7}"


Times = npt.NDArray[np.int64]


def truth_spikes(truth_t_ns: Times, truth_p_m: Array,
                 max_speed_mps: float = 5.0) -> npt.NDArray[np.bool_]:
    """Mask of truth samples that are spikes: reached *and* left faster than ``max_speed_mps``
    (a motion-capture glitch, e.g. a swapped marker). Interpolating across a spike would
    charge every method for the truth's error."""
    v = np.linalg.norm(np.diff(truth_p_m, axis=0), axis=1) / (np.diff(truth_t_ns) / 1e9)
    fast = v > max_speed_mps
    spikes = np.zeros(len(truth_t_ns), dtype=bool)
    spikes[1:-1] = fast[:-1] & fast[1:]
    return spikes


def score(t_ns: Times, position_m: Array, truth_t_ns: Times, truth_p_m: Array,
          covariances: Array | None = None, skip_s: float = 0.0) -> Accuracy:
    """RMSE against truth interpolated at the estimate times (estimates outside the truth's
    span, or in the first ``skip_s`` seconds of it, are left out)."""
    t0 = truth_t_ns[0] + skip_s * 1e9
    keep = (t_ns >= t0) & (t_ns <= truth_t_ns[-1])
    t, est = t_ns[keep], position_m[keep]
    truth = np.column_stack([np.interp(t, truth_t_ns, truth_p_m[:, i]) for i in range(3)])
    err = est - truth
    nees = float("nan")
    if covariances is not None:
        cov = covariances[keep]
        nees = float(np.mean([e @ np.linalg.solve(c, e) for e, c in zip(err, cov, strict=True)])
                     / 3)
    return Accuracy(len(t), float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1)))),
                    float(np.sqrt(np.mean(err[:, 2] ** 2))),
                    float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), nees)


def score_poses(poses: list[Pose], truth_t_ns: Times, truth_p_m: Array,
                skip_s: float = 0.0) -> Accuracy:
    t = np.array([p.t_ns for p in poses], dtype=np.int64)
    pos = np.array([p.position_m for p in poses])
    cov = np.array([np.array(p.covariance).reshape(6, 6)[:3, :3] for p in poses])
    return score(t, pos, truth_t_ns, truth_p_m, cov, skip_s)


class Method(Protocol):
    """What every compared method offers (the main filter via :class:`FilterMethod`)."""

    def predict(self, imu: ImuSample) -> None: ...

    def update(self, uwb: UwbRanges) -> object: ...

    def position(self) -> Array | None: ...


def run_method(method: Method, frames: Iterable[Frame]) -> tuple[Times, Array]:
    """Positions of ``method`` after every UWB epoch."""
    t: list[int] = []
    p: list[Array] = []
    for frame in frames:
        if isinstance(frame, ImuSample):
            method.predict(frame)
            continue
        if not isinstance(frame, UwbRanges):
            continue  # anchor-to-anchor ranges: not the tag's
        method.update(frame)
        pos = method.position()
        if pos is not None:
            t.append(frame.t_ns)
            p.append(pos)
    return np.array(t, dtype=np.int64), np.array(p).reshape(-1, 3)
