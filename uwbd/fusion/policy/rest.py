"""Rest: the recent IMU samples (body axes) and the rest test on them, and what the UWB
fixes say about motion.

At rest the specific force is steady (its spread is the sensor's noise plus a little
vibration) and close to ``g`` in size, and the rotation rate is small and steady. Slow
handheld motion has small accelerations too, but not the stillness of a sample set down:
the test asks for all four over ``span_s`` (the ZUPT window, 0.5 s by default; the start
asks for ``init_static_s``).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.noise import GRAVITY_MPS2
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.settings import RestLimits

Vec3 = tuple[float, float, float]
JUDGE_EVERY_NS = 20_000_000


class ImuWindow:
    def __init__(self, length_s: float, limits: RestLimits, gravity_mps2: float = GRAVITY_MPS2,
                 *, core: Core) -> None:
        self.length_ns = int(length_s * 1e9)
        self._core = core  # the window's moments: C, or the reference (None)
        self.limits = limits
        self.gravity_mps2 = gravity_mps2
        self._samples: collections.deque[tuple[float, ...]] = collections.deque()
        self._added = 0  # samples ever added
        self._array = np.zeros((0, 7))  # the window as an array, as of _array_added samples
        self._array_added = 0
        self._memo_key: tuple[object, ...] = ()
        self._memo_ns = 0.0
        self._memo = False

    @property
    def samples(self) -> collections.deque[tuple[float, ...]]:
        """The window's rows ``(t_ns, *acc, *gyro)``, oldest first."""
        return self._samples

    def add(self, t_ns: int, acc: Vec3, gyro: Vec3) -> None:
        samples = self._samples
        samples.append((t_ns, *acc, *gyro))
        self._added += 1
        oldest_ns = t_ns - self.length_ns
        while samples[0][0] < oldest_ns:
            samples.popleft()

    def add_rows(self, rows: list[tuple[float, ...]]) -> None:
        """Rows ``(t_ns, *acc, *gyro)`` in time order, as :meth:`add` takes them one by one."""
        samples = self._samples
        samples.extend(rows)
        self._added += len(rows)
        oldest_ns = rows[-1][0] - self.length_ns
        while samples[0][0] < oldest_ns:
            samples.popleft()

    def clear(self) -> None:
        self._samples.clear()
        self._array, self._array_added = np.zeros((0, 7)), self._added
        self._memo_key = ()

    def as_array(self) -> Array:
        """The window's samples as rows ``t, acc, gyro``: the array of the last call with the
        samples since appended and those since dropped cut off (made anew, the 400 samples
        of a 2 s window cost ~25 times as much)."""
        samples = self._samples
        new = self._added - self._array_added
        if new > len(samples) or not len(self._array):
            arr = np.array(samples).reshape(-1, 7)
        else:
            kept = self._array[self._array[:, 0] >= samples[0][0]]
            if new == 0:
                arr = kept
            else:
                recent = [samples[-k] for k in range(new, 0, -1)]
                arr = np.concatenate([kept, np.array(recent)])
        self._array, self._array_added = arr, self._added
        return arr

    def span_s(self) -> float:
        s = self._samples
        return (s[-1][0] - s[0][0]) / 1e9 if s else 0.0

    def means(self, span_s: float | None = None) -> tuple[Array, Array] | None:
        """Mean specific force and mean rate over the window (or its last ``span_s``),
        ``None`` when empty."""
        samples = self._samples
        if not samples:
            return None
        a = self.as_array()
        if span_s is not None:
            a = a[a[:, 0] >= a[-1, 0] - span_s * 1e9]
        m = a.mean(axis=0)
        return m[1:4], m[4:7]

    def static(self, span_s: float) -> bool:
        """At rest over the last ``span_s``, judged at most every ``JUDGE_EVERY_NS`` of
        samples (single ranges ask at 100+ Hz; rest does not come and go faster)."""
        samples = self._samples
        if not samples:
            return False
        last_ns = samples[-1][0]
        key = (span_s,)
        if key == self._memo_key and 0 <= last_ns - self._memo_ns < JUDGE_EVERY_NS:
            return self._memo
        self._memo_key, self._memo_ns, self._memo = key, last_ns, self._judge(span_s)
        return self._memo

    def _judge(self, span_s: float) -> bool:
        samples = self._samples
        if not samples or (samples[-1][0] - samples[0][0]) < 0.9 * span_s * 1e9:
            return False
        core = self._core
        if core is not None:  # the same numbers, from the rows themselves
            moments = core.window_moments(samples, span_s * 1e9)
            if moments is None:
                return False
            (ax, ay, az, gx, gy, gz), (sax, say, saz, sgx, sgy, sgz) = moments
        else:
            a = self.as_array()
            # the samples at or after the span's start (times ascend: one search), one block
            recent = a[int(np.searchsorted(a[:, 0], a[-1, 0] - span_s * 1e9)):, 1:]
            if len(recent) < 3:
                return False
            # mean and std (population) per axis, in numpy's own steps for them
            mean = recent.sum(axis=0) / len(recent)
            dev = recent - mean
            ax, ay, az, gx, gy, gz = mean.tolist()
            sax, say, saz, sgx, sgy, sgz = np.sqrt((dev * dev).sum(axis=0)
                                                   / len(recent)).tolist()
        lim = self.limits
        return (math.hypot(sax, say, saz) < lim.acc_std_mps2
                and abs(math.hypot(ax, ay, az) - self.gravity_mps2) < lim.gravity_tolerance_mps2
                and math.hypot(gx, gy, gz) < lim.gyro_rps
                and math.hypot(sgx, sgy, sgz) < lim.gyro_rps)


STILL_S, STILL_MPS = 1, 0.15  # at rest the UWB fixes of this long move slower than this
STILL_EVERY_NS, MIN_STILL_FIXES = 180_000_000, 5


class UwbStillness:
    """UWB-only fixes over the last ``STILL_S``: what the ranges alone say about motion,
    whatever a ZUPT does to the state's velocity (constant velocity looks like rest to an
    IMU)."""

    def __init__(self) -> None:
        self._fixes: collections.deque[tuple[int, Array]] = collections.deque()
        self._sigma_m = 0.0  # horizontal σ of the latest fix

    def wants_fix(self, t_ns: int) -> bool:
        return not self._fixes or t_ns - self._fixes[-1][0] >= STILL_EVERY_NS

    def add(self, t_ns: int, fix: LsqFix) -> None:
        self._fixes.append((t_ns, fix.position_m))
        cov = fix.covariance  # (np.trace costs more than its two terms)
        self._sigma_m = math.sqrt(max(float(cov[0, 0] + cov[1, 1]) / 2, 0.0))

    def forget_before(self, t_ns: int) -> None:
        fixes = self._fixes
        while fixes and fixes[0][0] < t_ns - STILL_S * 1e9:
            fixes.popleft()

    def clear(self) -> None:
        self._fixes.clear()

    def still(self, allow_noise: bool = False) -> bool:
        """The fixes do not show the vehicle moving: a line fit's horizontal speed below
        ``STILL_MPS`` (with ``allow_noise``, or below 3σ of what the fixes' noise gives).
        Too few fixes to tell: still, and the IMU decides."""
        fixes = self._fixes
        n = len(fixes)
        if n < MIN_STILL_FIXES:
            return True
        vx, vy = _velocity_xy(fixes)
        limit = STILL_MPS
        if allow_noise:
            span_s = max((fixes[-1][0] - fixes[0][0]) / 1e9, 1e-3)
            limit = max(limit, 3.0 * self._sigma_m * math.sqrt(12.0 / n) / span_s)
        return math.hypot(vx, vy) < limit


def _velocity_xy(fixes: collections.deque[tuple[int, Array]]) -> tuple[float, float]:
    """:func:`uwbd.fusion.policy.alignment.velocity_fit`'s horizontal velocity in floats, on times
    from the first fix (exact, where Unix-epoch ns as float64 lose 256 ns): it runs at every
    update, on a handful of fixes."""
    t0 = fixes[0][0]
    ts = [(t - t0) / 1e9 for t, _ in fixes]
    xs = [float(p[0]) for _, p in fixes]
    ys = [float(p[1]) for _, p in fixes]
    n = len(ts)
    tm, xm, ym = sum(ts) / n, sum(xs) / n, sum(ys) / n
    stt = sxt = syt = 0.0
    for t, x, y in zip(ts, xs, ys, strict=True):
        dt = t - tm
        stt += dt * dt
        sxt += dt * (x - xm)
        syt += dt * (y - ym)
    stt = max(stt, 1e-9)
    return sxt / stt, syt / stt
