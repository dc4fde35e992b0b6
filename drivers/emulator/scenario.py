"""A built-in scenario for the emulator: a ground robot that rests, then drives a circle.

Navigation frame ENU, body frame forward-left-up; the emulated IMU is mounted along the body
axes. The trajectory is closed-form (no integration drift between IMU and ranges):

* rest for ``rest_s``; then the speed rises smoothly (smoothstep) to ``speed_mps`` over
  ``ramp_s`` and stays there, on a circle of ``radius_m`` about ``centre_m``, anticlockwise;
* IMU: specific force ``f_b = R_bn (a_n + g ẑ)`` and angular rate about z, plus a constant
  bias and white noise; ranges: true distance to each anchor plus white noise.

Each stream draws from its own seeded generator, so frames are reproducible per seed.
The fusion issue's simulator supersedes this for accuracy work; this one only has to be
physically consistent and cheap.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from drivers.frames import AnchorRange, ImuSample, UwbRanges

GRAVITY_MPS2 = 9.80665
DEFAULT_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (-5.0, 30.0, 0.0), (-5.0, -30.0, 0.0), (10.0, 10.0, 5.0),
    (10.0, -10.0, 5.0), (20.0, 30.0, 0.0), (20.0, -30.0, 0.0),
)


@dataclass(frozen=True)
class CircleScenario:
    """Parameters of the rest-then-circle trajectory and its sensors."""

    rest_s: float = 2.0
    ramp_s: float = 2.0
    speed_mps: float = 1.0
    radius_m: float = 4.0
    centre_m: tuple[float, float, float] = (7.0, 0.0, 0.5)
    anchors_m: tuple[tuple[float, float, float], ...] = DEFAULT_ANCHORS_M
    imu_rate_hz: float = 200.0
    uwb_rate_hz: float = 10.0
    acc_noise_mps2: float = 0.02
    gyro_noise_rps: float = 0.002
    acc_bias_mps2: tuple[float, float, float] = (0.05, -0.03, 0.02)
    gyro_bias_rps: tuple[float, float, float] = (0.002, -0.001, 0.003)
    range_noise_m: float = 0.05
    seed: int = 0

    def _motion(self, t_s: float) -> tuple[float, float, float]:
        """Arc angle θ (rad), speed v (m/s) and its rate v̇ (m/s²) at time ``t_s``."""
        u = min(max((t_s - self.rest_s) / self.ramp_s, 0.0), 1.0)
        w = self.speed_mps / self.radius_m
        v = self.speed_mps * (3 * u**2 - 2 * u**3)
        v_dot = self.speed_mps * (6 * u - 6 * u**2) / self.ramp_s
        theta = w * self.ramp_s * (u**3 - u**4 / 2)  # ∫ smoothstep over the ramp
        if t_s > self.rest_s + self.ramp_s:
            theta += w * (t_s - self.rest_s - self.ramp_s)
        return theta, v, v_dot

    def heading_rad(self, t_s: float) -> float:
        """True heading (yaw from east, counter-clockwise): along the circle's tangent."""
        return self._motion(t_s)[0]

    def position_m(self, t_s: float) -> tuple[float, float, float]:
        """True position (ENU, m): the circle starts at the point due south of the centre."""
        theta, _, _ = self._motion(t_s)
        cx, cy, cz = self.centre_m
        a = theta - math.pi / 2
        return (cx + self.radius_m * math.cos(a), cy + self.radius_m * math.sin(a), cz)

    def imu(self, duration_s: float | None = None) -> Iterator[tuple[int, ImuSample]]:
        """(time offset ns, sample) pairs; endless when ``duration_s`` is None."""
        rng = np.random.default_rng([self.seed, 1])
        for t_ns in _ticks(self.imu_rate_hz, duration_s):
            heading, v, v_dot = self._motion(t_ns / 1e9)
            # body frame: forward along the tangent, left towards the centre
            f_b = (v_dot, v * v / self.radius_m, GRAVITY_MPS2)
            noise = rng.normal(size=6)
            acc = tuple(f + b + self.acc_noise_mps2 * n
                        for f, b, n in zip(f_b, self.acc_bias_mps2, noise[:3], strict=True))
            w_b = (0.0, 0.0, v / self.radius_m)
            gyro = tuple(w + b + self.gyro_noise_rps * n
                         for w, b, n in zip(w_b, self.gyro_bias_rps, noise[3:], strict=True))
            # with the device's own attitude (0x53), as a WitMotion sends it by default
            yaw_deg = math.degrees(math.remainder(heading, math.tau))
            yield t_ns, ImuSample(t_ns, _v3(acc), _v3(gyro), temperature_c=25.0,
                                  angle_deg=(0.0, 0.0, yaw_deg))

    def uwb(self, duration_s: float | None = None) -> Iterator[tuple[int, UwbRanges]]:
        """(time offset ns, ranging epoch) pairs with anchor ids 0..n-1."""
        rng = np.random.default_rng([self.seed, 2])
        for t_ns in _ticks(self.uwb_rate_hz, duration_s):
            p = self.position_m(t_ns / 1e9)
            noise = rng.normal(size=len(self.anchors_m) + 3)
            ranges = tuple(
                AnchorRange(i, max(math.dist(p, a) + self.range_noise_m * noise[i], 0.01),
                            None, a)
                for i, a in enumerate(self.anchors_m))
            fix = _v3(x + self.range_noise_m * n for x, n in zip(p, noise[-3:], strict=True))
            yield t_ns, UwbRanges(t_ns, ranges, tag_position_m=fix, quality=90.0)


def _ticks(rate_hz: float, duration_s: float | None) -> Iterator[int]:
    """Sample times (ns from the start) at ``rate_hz``, up to ``duration_s`` or forever."""
    period_ns = round(1e9 / rate_hz)
    k = 0
    while duration_s is None or k * period_ns <= duration_s * 1e9:
        yield k * period_ns
        k += 1


def _v3(values: Iterable[float]) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return (x, y, z)
