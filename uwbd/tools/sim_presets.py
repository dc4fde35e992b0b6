"""The simulator's set-ups (:class:`~uwbd.tools.simulator.SimConfig` presets): the default
layout, a ground robot in a room with ceiling anchors, a handheld tag ranging one anchor at a
time; and a run's motion cut or repeated to a duration (``uwbd simulate --duration``)."""

from __future__ import annotations

import math
from collections.abc import Callable

from uwbd.tools.simulator import DEFAULT_SEGMENTS, SimConfig

_QUARTER = math.pi / 2  # a 90 deg turn lasts _QUARTER / yaw rate

ROOM_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (0.3, 0.3, 2.40), (7.7, 0.3, 2.55), (7.7, 5.7, 2.35), (0.3, 5.7, 2.50),
)
# a ground robot in the 8 x 6 m room: x 1.5..6.7, y 1.2..4.4, z 0.35..0.57 m; 76 s
ROOM_SEGMENTS: tuple[tuple[float, float, float, float], ...] = (
    (5.0, 0.0, 0.0, 0.0),  # still start
    (7.0, 0.6, 0.0, 0.0),  # east
    (_QUARTER / 0.5, 0.5, 0.5, 0.0),  # left turn -> north
    (4.0, 0.5, 0.0, 0.03),  # up a ramp
    (3.0, 0.0, 0.0, 0.0),  # stop
    (_QUARTER / 0.6, 0.0, 0.6, 0.0),  # spin on the spot -> west
    (6.0, 0.7, 0.0, 0.0),
    (_QUARTER / 0.5, 0.4, 0.5, 0.0),  # left turn -> south
    (2.0, 0.3, 0.0, -0.05),  # down a ramp
    (3.0, 0.0, 0.0, 0.0),  # stop
    (_QUARTER / 0.5, 0.0, 0.5, 0.0),  # spin on the spot -> east
    (5.0, 0.8, 0.0, 0.0),
    (2 * _QUARTER / 0.5, 0.4, 0.5, 0.0),  # U-turn -> west
    (4.0, 0.6, 0.0, -0.03),  # down a ramp
    (2.5, 0.0, 0.0, 0.0),  # stop
    (_QUARTER / 0.5, 0.4, 0.5, 0.0),  # left turn -> south
    (2.0, 0.5, 0.0, 0.03),  # up a ramp
    (_QUARTER / 0.5, 0.4, 0.5, 0.0),  # left turn -> east
    (3.0, 0.4, 0.0, 0.0),
    (5.0, 0.0, 0.0, 0.0),  # still end
)

HANDHELD_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (0.2, 0.2, 0.30), (5.8, 0.2, 0.28), (5.8, 4.8, 0.32), (0.2, 4.8, 0.31),  # low
    (0.2, 0.2, 2.30), (5.8, 0.2, 2.33), (5.8, 4.8, 2.28), (0.2, 4.8, 2.31),  # high
)
# carried through the 6 x 5 m room: x 1.1..4.6, y 0.8..3.4, z 1.01..1.22 m; 59 s
HANDHELD_SEGMENTS: tuple[tuple[float, float, float, float], ...] = (
    (4.0, 0.0, 0.0, 0.0),  # held still
    (5.0, 0.4, 0.0, 0.0),  # walk east
    (_QUARTER / 0.3, 0.3, 0.3, 0.0),  # gentle left -> north
    (3.0, 0.3, 0.0, 0.04),  # lifted a little
    (3.0, 0.0, 0.0, 0.0),  # pause
    (_QUARTER / 0.3, 0.0, 0.3, -0.02),  # turn on the spot -> west, lowered
    (5.0, 0.4, 0.0, 0.0),
    (_QUARTER / 0.25, 0.3, 0.25, 0.0),  # gentle left -> south
    (2.0, 0.2, 0.0, 0.0),
    (4.0, 0.0, 0.0, 0.0),  # pause
    (_QUARTER / 0.3, 0.3, 0.3, -0.02),  # gentle left -> east
    (4.0, 0.4, 0.0, 0.02),
    (4.0, 0.25, 0.2, 0.0),  # gentle left
    (3.0, 0.0, 0.0, 0.0),  # pause
)


def segments_for(duration_s: float,
                 segments: tuple[tuple[float, float, float, float], ...] = DEFAULT_SEGMENTS
                 ) -> tuple[tuple[float, float, float, float], ...]:
    """``segments`` repeated or cut to last ``duration_s`` seconds in all (the last one
    shortened)."""
    if duration_s <= 0:
        raise ValueError("the duration must be positive")
    out: list[tuple[float, float, float, float]] = []
    left = duration_s
    while left > 1e-9:
        for seg in segments:
            if left <= 1e-9:
                break
            out.append((min(seg[0], left), *seg[1:]))
            left -= seg[0]
    return tuple(out)


def seed_layout(seed: int = 0) -> SimConfig:
    """The default run: 6 anchors over a 25 x 60 m area, 10 Hz epochs, 200 Hz IMU."""
    return SimConfig(seed=seed)


def ceiling_room(seed: int = 0) -> SimConfig:
    """A ground robot driving slowly (0.3-0.8 m/s, turns, spins, stops, small ramps) in an
    8 x 6 m room, tag at 0.35-0.57 m, 4 anchors near the corners at 2.35-2.55 m (nearly
    coplanar: height poorly observed), lever arm 0.27 m up, NLOS bursts, anchor 2 out
    from 28 s for 20 s; 76 s."""
    return SimConfig(segments=ROOM_SEGMENTS, start_m=(1.5, 1.2, 0.45), anchors_m=ROOM_ANCHORS_M,
                     lever_arm_m=(0.0, 0.0, 0.27), anchor_outages_s=((2, 28.0, 20.0),),
                     ground_vehicle=True, seed=seed)


def handheld_async(seed: int = 0) -> SimConfig:
    """Carried slowly (0.2-0.5 m/s, pauses, gentle turns) through a 6 x 5 m room at ~1.1 m,
    8 anchors (4 at ~0.3 m, 4 at ~2.3 m, at the corners), one range per message
    round-robin at 170 Hz in total, IMU at 100 Hz, NLOS five times as often on the low
    anchors; 59 s."""
    return SimConfig(segments=HANDHELD_SEGMENTS, start_m=(1.3, 1.5, 1.1),
                     anchors_m=HANDHELD_ANCHORS_M, imu_rate_hz=100.0, uwb_rate_hz=170.0,
                     uwb_schedule="round_robin", range_noise_m=0.10,
                     anchor_nlos_rate_hz=(0.05,) * 4 + (0.01,) * 4, seed=seed)


PRESETS: dict[str, Callable[[int], SimConfig]] = {
    "seed_layout": seed_layout, "ceiling_room": ceiling_room, "handheld_async": handheld_async,
}
