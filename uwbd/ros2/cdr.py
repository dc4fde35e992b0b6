"""CDR of the live topics' messages without building a message object per sample.

The pose, odometry, transform and IMU messages are, once their frame ids are fixed, the same
bytes but for a stamp (``int32`` seconds, ``uint32`` nanoseconds) and a run of ``float64``s at
the end. :class:`FixedLayout` learns where those are from rosbags' own serialisation of two
probes that differ only in their stamp, and then writes a sample as the constant bytes, the
stamp and the numbers: about a tenth of building the message and serialising it (the cost
that mattered, ROS 2 topics being published at the IMU's rate). Each layout is checked
against rosbags when it is made (:func:`layout_of`), and the tests compare the two on random
messages.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from typing import Any

from drivers.frames import ImuSample
from uwbd.fusion.types import Pose
from uwbd.ros2.messages import (
    TYPES,
    TYPESTORE,
    FrameIds,
    imu_msg,
    imu_values,
    odometry_msg,
    odometry_values,
    pose_msg,
    pose_values,
    tf_msg,
    tf_values,
)

STAMP = struct.Struct("<iI")
# a probe's stamp whose eight bytes all differ from a zero stamp's: 0x01010101 s and ns
PROBE_T_NS = 0x01010101 * 1_000_000_000 + 0x01010101


class FixedLayout:
    """A message type's bytes: constant head, the stamp, constant tail, ``n`` doubles."""

    def __init__(self, zero_stamp: bytes, probe_stamp: bytes, n_doubles: int) -> None:
        size = 8 * n_doubles
        if len(zero_stamp) != len(probe_stamp) or len(zero_stamp) < size + STAMP.size:
            raise ValueError("the probes are not one fixed layout")
        head0, head1 = zero_stamp[:-size], probe_stamp[:-size]
        differ = [i for i, (a, b) in enumerate(zip(head0, head1, strict=True)) if a != b]
        if not differ or differ[-1] - differ[0] != STAMP.size - 1:
            raise ValueError("the probes do not differ in one stamp")
        at = differ[0]
        self._head, self._tail = head0[:at], head0[at + STAMP.size:]
        self._doubles = struct.Struct(f"<{n_doubles}d")

    def pack(self, t_ns: int, values: Sequence[float]) -> bytes:
        sec, nsec = divmod(t_ns, 1_000_000_000)
        return b"".join((self._head, STAMP.pack(sec, nsec), self._tail,
                         self._doubles.pack(*values)))


def layout_of(serialize: Callable[[Any], bytes], values: Callable[[Any], Sequence[float]],
              probe: Callable[[int], Any]) -> FixedLayout:
    """The layout of the messages ``serialize`` makes of objects such as ``probe(t_ns)``
    (alike but for their time), whose numbers are ``values(obj)``; ``ValueError`` if packing
    them is not byte for byte what ``serialize`` writes."""
    zero, other = probe(0), probe(PROBE_T_NS)
    layout = FixedLayout(serialize(zero), serialize(other), len(values(zero)))
    if layout.pack(PROBE_T_NS, values(other)) != serialize(other):
        raise ValueError("packing the numbers does not give the serialised message")
    return layout


# -- the live topics' layouts ------------------------------------------------------------


Values = Callable[[Pose], Sequence[float]]


def _serializer(msgtype: str, msg_of: Callable[[Any], object]) -> Callable[[Any], bytes]:
    return lambda obj: bytes(TYPESTORE.serialize_cdr(msg_of(obj), msgtype))


def _probe_pose(t_ns: int) -> Pose:
    """A pose of distinct numbers, for learning the layouts (a unit quaternion, since the
    odometry rotates its velocity by it)."""
    w = math.sqrt(1 - 0.1 ** 2 - 0.2 ** 2 - 0.3 ** 2)
    return Pose(t_ns, (1.5, -2.25, 0.125), (0.5, 0.25, -0.125), (0.1, 0.2, 0.3, w),
                tuple(0.01 * (k + 1) for k in range(36)), "", True)


def pose_layouts(frames: FrameIds) -> dict[str, tuple[FixedLayout, Values]]:
    """The layouts of the messages made at each pose, by role, with their numbers."""
    makers: dict[str, tuple[Callable[[Pose, FrameIds], object], Values]] = {
        "pose": (pose_msg, pose_values), "odom": (odometry_msg, odometry_values),
        "tf": (tf_msg, tf_values)}
    def serializer(role: str) -> Callable[[Any], bytes]:
        msg_of = makers[role][0]
        return _serializer(TYPES[role], lambda pose: msg_of(pose, frames))
    return {role: (layout_of(serializer(role), values, _probe_pose), values)
            for role, (_, values) in makers.items()}


def imu_layout(frames: FrameIds) -> FixedLayout:
    def probe(t_ns: int) -> ImuSample:
        return ImuSample(t_ns, (0.1, -0.2, 9.8), (0.01, -0.02, 0.03))
    return layout_of(_serializer(TYPES["imu"], lambda s: imu_msg(s, frames, 1e-4, 2e-3)),
                     lambda s: imu_values(s, 1e-4, 2e-3), probe)
