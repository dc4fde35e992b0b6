"""Typed frames that every driver produces and every encoder consumes.

Conventions (docs/architecture.md, "The data's way"):

* ``t_ns`` is the host receive time of the frame's last byte, integer nanoseconds since the
  Unix epoch (``time.time_ns()``). Parsers have no clock: the source passes the receive time of
  each read to ``feed(data, t_ns)`` and the frame completed by that read carries it.
* Units are in field names. Vectors are tuples, so frames are immutable, hashable and compare
  exactly (``parse(encode(f)) == f``).
* Axes are the *sensor's own* axes as sent on the wire; the mounting rotation into the body
  frame (forward-left-up) is applied by the fusion layer, not here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from drivers import accel

Vec3 = tuple[float, float, float]
Quat4 = tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU measurement in the sensor's axes.

    ``device_time_ns`` is the sensor's own clock when it sends one (WitMotion 0x50 packet:
    calendar time; Nooploop: system time), kept for de-jittering, never used as ``t_ns``.
    ``angle_deg`` (roll, pitch, yaw) and ``quaternion_wire`` (wire order q0..q3) are the
    device's own attitude solution; ``mag_raw`` is the magnetometer in device LSB.
    """

    t_ns: int
    acc_mps2: Vec3
    gyro_rps: Vec3
    temperature_c: float | None = None
    angle_deg: Vec3 | None = None
    mag_raw: tuple[int, int, int] | None = None
    quaternion_wire: Quat4 | None = None
    device_time_ns: int | None = None


@dataclass(frozen=True, slots=True)
class AnchorRange:
    """One tag-to-anchor distance as the device reported it.

    ``quality`` is what the device says about this range on a 0-100 scale (100: trust it
    fully; the filter scales the range variance by ``100/quality``): DWM1001 TLV's
    per-distance qf; for Nooploop NodeFrame2 it is derived from the two RSSIs
    (:func:`drivers.nlink_node2.nlos_quality`); ``None`` when the device says nothing.
    ``anchor_position_m`` is the anchor position the device sends with the range (DWM1001),
    ``None`` when positions come from configuration. ``fp_rssi_dbm`` and ``rx_rssi_dbm`` are
    the first-path and total received power of the range's last message (Nooploop
    NodeFrame2), ``None`` elsewhere; ``rx - fp`` above about 6 dB suggests NLOS.
    """

    anchor_id: int
    range_m: float
    quality: float | None = None
    anchor_position_m: Vec3 | None = None
    fp_rssi_dbm: float | None = None
    rx_rssi_dbm: float | None = None


@dataclass(frozen=True, slots=True)
class UwbRanges:
    """One ranging epoch of a UWB tag: the ranges plus the tag's own solution, if any.

    ``quality`` is the device's position quality factor (DWM1001 qf, 0-100);
    ``tag_position_error_m`` its estimated position error (Nooploop eop);
    ``device_time_ms`` the tag's own millisecond clock (Nooploop system_time).
    """

    t_ns: int
    ranges: tuple[AnchorRange, ...]
    tag_position_m: Vec3 | None = None
    quality: float | None = None
    tag_velocity_mps: Vec3 | None = None
    tag_position_error_m: Vec3 | None = None
    tag_id: int | None = None
    device_time_ms: int | None = None


@dataclass(frozen=True, slots=True)
class AnchorPair:
    """One anchor-to-anchor range (``anchor_a < anchor_b``)."""

    anchor_a: int
    anchor_b: int
    range_m: float


@dataclass(frozen=True, slots=True)
class AnchorRanges:
    """Anchor-to-anchor ranges, for surveying the anchors (TREK1000 ``ma``); never fused.

    The anchors measure them between themselves; anchor A0 reports them. ``pairs`` holds
    an :class:`AnchorPair` per range; ``device_time_ms`` is the reporting anchor's
    millisecond tick.
    """

    t_ns: int
    pairs: tuple[AnchorPair, ...]
    device_time_ms: int | None = None


Frame = ImuSample | UwbRanges | AnchorRanges
"""What parsers emit. Consumers act on the types they know and pass over the others: the
filter fuses ``ImuSample`` and ``UwbRanges`` only."""


def retimed(frame: Frame, t_ns: int) -> Frame:
    """``frame`` with ``t_ns`` set (``dataclasses.replace(frame, t_ns=t_ns)``, the
    reference; with the drivers' C, one call: a frozen dataclass's ``__init__`` costs
    ~10 µs on a small machine, and a batched read re-times every sample it holds)."""
    fast = accel.frames
    if fast is not None:
        copy: Frame = fast.retimed(frame, t_ns)
        return copy
    return dataclasses.replace(frame, t_ns=t_ns)
