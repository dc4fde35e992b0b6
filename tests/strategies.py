"""Hypothesis strategies: frames whose values lie on each wire format's grid, so that
``parse(encode(f)) == f`` must hold exactly."""

from __future__ import annotations

import datetime as dt

from hypothesis import strategies as st

from drivers import nlink_node2, wit
from drivers.frames import AnchorPair, AnchorRange, AnchorRanges, ImuSample, UwbRanges

i16 = st.integers(-0x8000, 0x7FFF)
i24 = st.integers(-0x800000, 0x7FFFFF)
i32 = st.integers(-0x80000000, 0x7FFFFFFF)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


def vec(raw: st.SearchStrategy[int], div: float, n: int = 3) -> st.SearchStrategy[tuple]:
    return st.tuples(*[raw.map(lambda r: r / div)] * n)


def wit_streams(max_size: int = 5) -> st.SearchStrategy[list[ImuSample]]:
    """Samples of one device configuration: the same optional packets in every cycle."""
    return st.tuples(*[st.booleans()] * 4).flatmap(
        lambda cfg: st.lists(wit_samples(*cfg), min_size=1, max_size=max_size))


@st.composite
def wit_samples(draw: st.DrawFn, angle: bool, mag: bool, quat: bool, time: bool) -> ImuSample:
    stamp = draw(st.datetimes(dt.datetime(2000, 1, 1), dt.datetime(2099, 12, 31)))
    ms = stamp.microsecond // 1000
    time_ns = int(stamp.replace(microsecond=0, tzinfo=dt.timezone.utc).timestamp()) * 10**9
    return ImuSample(
        t_ns=0,
        acc_mps2=draw(vec(i16, wit.ACC_DIV)),
        gyro_rps=draw(vec(i16, wit.GYRO_DIV)),
        temperature_c=draw(i16.map(lambda r: r / wit.TEMP_DIV)),
        angle_deg=draw(vec(i16, wit.ANGLE_DIV)) if angle else None,
        mag_raw=draw(st.tuples(i16, i16, i16)) if mag else None,
        quaternion_wire=draw(vec(i16, wit.QUAT_DIV, 4)) if quat else None,
        device_time_ns=time_ns + ms * 10**6 if time else None,
    )


centi = st.integers(-99999, 99999).map(lambda k: k / 100)


@st.composite
def dwm_shell_epochs(draw: st.DrawFn) -> UwbRanges:
    n = draw(st.integers(0, 8))
    ranges = tuple(
        AnchorRange(draw(st.integers(0, 0xFFFF)), draw(st.integers(0, 99999)) / 100, None,
                    (draw(centi), draw(centi), draw(centi)))
        for _ in range(n))
    if draw(st.booleans()):
        return UwbRanges(0, ranges, (draw(centi), draw(centi), draw(centi)),
                         float(draw(st.integers(0, 100))))
    return UwbRanges(0, ranges)


@st.composite
def dwm_tlv_epochs(draw: st.DrawFn) -> UwbRanges:
    milli = i32.map(lambda r: r / 1000)
    ranges = tuple(
        AnchorRange(draw(st.integers(0, 0xFFFF)), draw(st.integers(0, 2**32 - 1)) / 1000,
                    float(draw(st.integers(0, 100))), (draw(milli), draw(milli), draw(milli)))
        for _ in range(draw(st.integers(0, 12))))
    return UwbRanges(0, ranges, (draw(milli), draw(milli), draw(milli)),
                     float(draw(st.integers(0, 100))))


@st.composite
def nlink_epochs(draw: st.DrawFn) -> UwbRanges:
    slots = draw(st.lists(st.integers(0, 7), unique=True, max_size=8).map(sorted))
    nonzero = i24.filter(lambda r: r != 0).map(lambda r: r / 1000)
    return UwbRanges(
        t_ns=0,
        ranges=tuple(AnchorRange(k, draw(nonzero)) for k in slots),
        tag_position_m=draw(vec(i24, 1000)),
        tag_velocity_mps=draw(vec(i24, 10000)),
        tag_position_error_m=draw(vec(st.integers(0, 255), 100)),
        tag_id=draw(st.integers(0, 255)),
        device_time_ms=draw(st.integers(0, 2**32 - 1)),
    )


@st.composite
def nlink_imus(draw: st.DrawFn) -> ImuSample:
    return ImuSample(
        t_ns=0, acc_mps2=draw(st.tuples(f32, f32, f32)), gyro_rps=draw(st.tuples(f32, f32, f32)),
        angle_deg=draw(vec(i16, 100)), quaternion_wire=draw(st.tuples(f32, f32, f32, f32)),
    )


@st.composite
def trek_epochs(draw: st.DrawFn, raw: bool = False) -> UwbRanges:
    """An ``mc`` epoch (``raw``: an ``mr`` one, which carries no time): ranges in whole mm
    (signed: a bias-corrected range may be negative) to a subset of A0..A3."""
    anchors = draw(st.lists(st.integers(0, 3), unique=True, max_size=4).map(sorted))
    return UwbRanges(
        t_ns=0, ranges=tuple(AnchorRange(k, draw(i32) / 1000) for k in anchors),
        tag_id=draw(st.integers(0, 255)),
        device_time_ms=None if raw else draw(st.integers(0, 2**32 - 1)))


@st.composite
def trek_anchor_ranges(draw: st.DrawFn) -> AnchorRanges:
    """An ``ma`` report: some of the pairs A0-A1, A0-A2, A1-A2, in that order."""
    pairs = draw(st.lists(st.sampled_from([(0, 1), (0, 2), (1, 2)]), unique=True).map(sorted))
    return AnchorRanges(0, tuple(AnchorPair(a, b, draw(i32) / 1000) for a, b in pairs),
                        draw(st.integers(0, 2**32 - 1)))


@st.composite
def node2_epochs(draw: st.DrawFn, max_nodes: int = 12) -> UwbRanges:
    """A NodeFrame2 epoch: RSSIs on the wire's 0.5 dB grid, quality derived from them."""
    ranges = []
    for _ in range(draw(st.integers(0, max_nodes))):
        fp, rx = (draw(st.integers(0, 255)) / nlink_node2.RSSI_DIV for _ in range(2))
        ranges.append(AnchorRange(draw(st.integers(0, 255)), draw(i24) / 1000,
                                  nlink_node2.nlos_quality(fp, rx), fp_rssi_dbm=fp,
                                  rx_rssi_dbm=rx))
    return UwbRanges(
        t_ns=0, ranges=tuple(ranges),
        tag_position_m=draw(vec(i24, 1000)),
        tag_velocity_mps=draw(vec(i24, 10000)),
        tag_position_error_m=draw(vec(st.integers(0, 255), 100)),
        tag_id=draw(st.integers(0, 255)),
        device_time_ms=draw(st.integers(0, 2**32 - 1)),
    )
