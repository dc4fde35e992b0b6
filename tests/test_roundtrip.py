"""parse(encode(f)) == f for every frame type, on hypothesis-generated values."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import (
    dwm_shell_epochs,
    dwm_tlv_epochs,
    nlink_epochs,
    nlink_imus,
    node2_epochs,
    trek_anchor_ranges,
    trek_epochs,
    wit_streams,
)

from drivers import PARSERS, dwm1001, dwm1001_tlv, nlink, nlink_node2, trek1000, wit
from drivers.frames import AnchorPair, AnchorRange, AnchorRanges, ImuSample, UwbRanges
from drivers.layout import Field, Layout


def parse_all(driver: str, data: bytes, t_ns: int = 7) -> list:
    parser = PARSERS[driver]()
    frames = parser.feed(data, t_ns) + parser.flush()
    assert parser.stats.bytes_skipped == 0
    assert parser.stats.checksum_errors == parser.stats.malformed == 0
    return frames


def at(frame, t_ns: int = 7):
    return dataclasses.replace(frame, t_ns=t_ns)


@given(wit_streams())
def test_wit_round_trip(samples: list[ImuSample]) -> None:
    data = b"".join(wit.encode(s) for s in samples)
    assert parse_all("wit", data) == [at(s) for s in samples]


def test_wit_cycle_closes_on_its_last_packet_without_waiting() -> None:
    """Once the cycle is learned, a sample leaves with the cycle's last packet."""
    sample = ImuSample(0, (0.0, 0.0, 9.80665), (0.0, 0.0, 0.0), 25.0, angle_deg=(45.0, -90.0, 90.0))
    parser = wit.WitParser()
    assert parser.feed(wit.encode(sample), 1) == []  # not learned yet: waits for the wrap
    assert parser.feed(wit.encode(sample), 2) == [at(sample, 1), at(sample, 2)]
    assert parser.feed(wit.encode(sample), 3) == [at(sample, 3)]


def test_wit_relearns_when_the_device_adds_a_packet_type() -> None:
    short = ImuSample(0, (0.0, 0.0, 9.80665), (0.0, 0.0, 0.0), 25.0)
    longer = dataclasses.replace(short, mag_raw=(1, 2, 3))
    parser = wit.WitParser()
    frames = parser.feed(wit.encode(short) * 3 + wit.encode(longer) * 4, 0) + parser.flush()
    # the first longer cycle is cut at the old closing type and its mag packet dropped
    assert frames == [short] * 3 + [short] + [longer] * 3
    assert parser.stats.dropped == 1


@given(dwm_shell_epochs())
def test_dwm1001_shell_round_trip(epoch) -> None:
    assert parse_all("dwm1001", dwm1001.encode(epoch)) == [at(epoch)]


@given(dwm_tlv_epochs())
def test_dwm1001_tlv_round_trip(epoch) -> None:
    assert parse_all("dwm1001-tlv", dwm1001_tlv.encode(epoch)) == [at(epoch)]


@given(nlink_epochs())
def test_nlink_round_trip(epoch) -> None:
    assert parse_all("nlink", nlink.encode(epoch)) == [at(epoch)]


@given(nlink_epochs(), nlink_imus())
def test_nlink_round_trip_with_tag_imu(epoch, imu: ImuSample) -> None:
    parser = nlink.NlinkParser(emit_imu=True)
    frames = parser.feed(nlink.encode(epoch, imu), 7)
    expected_imu = dataclasses.replace(imu, t_ns=7, device_time_ns=epoch.device_time_ms * 10**6)
    assert frames == [at(epoch), expected_imu]


@given(node2_epochs())
def test_nlink_node2_round_trip(epoch) -> None:
    assert parse_all("nlink-node2", nlink_node2.encode(epoch)) == [at(epoch)]


@given(node2_epochs(max_nodes=3), nlink_imus())
def test_nlink_node2_round_trip_with_tag_imu(epoch, imu: ImuSample) -> None:
    parser = nlink_node2.NlinkNode2Parser(emit_imu=True)
    frames = parser.feed(nlink_node2.encode(epoch, imu), 7)
    expected_imu = dataclasses.replace(imu, t_ns=7, device_time_ns=epoch.device_time_ms * 10**6)
    assert frames == [at(epoch), expected_imu]


def test_nlink_node2_largest_frame_round_trips() -> None:
    epoch = UwbRanges(0, tuple(AnchorRange(k, k / 1000, 100.0, fp_rssi_dbm=-80.0,
                                           rx_rssi_dbm=-76.0) for k in range(255)))
    data = nlink_node2.encode(epoch)
    assert len(data) == nlink_node2.MAX_LEN == 119 + 13 * 255 + 1
    (frame,) = parse_all("nlink-node2", data)
    assert frame.ranges == epoch.ranges


@given(trek_epochs(), st.integers(0, 0xFFFF), st.integers(0, 0xFF))
def test_trek1000_round_trip(epoch, count: int, seq: int) -> None:
    """mc feeds the fusion; the mr line that follows it is checked and skipped."""
    assert parse_all("trek1000", trek1000.encode(epoch, False, count, seq)) == [at(epoch)]
    both = trek1000.encode(epoch, True, count, seq)
    parser = trek1000.Trek1000Parser()
    assert parser.feed(both, 7) == [at(epoch)]
    assert parser.stats.bytes_skipped == len(both) // 2 and parser.stats.malformed == 0


@given(trek_epochs(raw=True))
def test_trek1000_raw_round_trip(epoch) -> None:
    """trek1000-raw takes the mr line's ranges and skips the mc line."""
    parser = PARSERS["trek1000-raw"]()
    mr = trek1000.encode(epoch)
    assert parser.feed(mr, 7) == [at(epoch)]
    assert parser.stats.bytes_skipped == len(mr) // 2


@given(trek_anchor_ranges())
def test_trek1000_anchor_ranges_round_trip(report: AnchorRanges) -> None:
    for driver in ("trek1000", "trek1000-raw"):
        assert parse_all(driver, trek1000.encode(report)) == [at(report)]


def test_trek1000_encoder_refuses_what_the_lines_cannot_carry() -> None:
    with pytest.raises(ValueError, match=r"A0\.\.A3"):
        trek1000.encode(UwbRanges(0, (AnchorRange(4, 1.0),)))
    with pytest.raises(ValueError, match="twice"):
        trek1000.encode(UwbRanges(0, (AnchorRange(1, 1.0), AnchorRange(1, 2.0))))
    with pytest.raises(ValueError, match="hex digits"):
        trek1000.encode(UwbRanges(0, (AnchorRange(0, 3e6),)))
    with pytest.raises(ValueError, match="pair"):
        trek1000.encode(AnchorRanges(0, (AnchorPair(0, 3, 1.0),)))


def test_nlink_node2_encoder_refuses_what_the_frame_cannot_carry() -> None:
    with pytest.raises(ValueError, match="node id"):
        nlink_node2.encode(UwbRanges(0, (AnchorRange(256, 1.0),)))
    with pytest.raises(ValueError, match="at most 255"):
        nlink_node2.encode(UwbRanges(0, tuple(AnchorRange(k % 256, 1.0) for k in range(256))))


def test_dwm1001_tlv_encoder_refuses_a_quality_above_100() -> None:
    with pytest.raises(ValueError, match="quality"):
        dwm1001_tlv.encode(UwbRanges(0, (AnchorRange(1, 1.0, 101.0),), (0.0, 0.0, 0.0), 50.0))


@pytest.mark.parametrize(("gap_db", "quality"), [
    (-3.0, 100.0), (6.0, 100.0), (7.0, 90.0), (10.0, 60.0), (15.5, 5.0), (16.0, 0.0),
    (30.0, 0.0)])
def test_nlos_quality_scale(gap_db: float, quality: float) -> None:
    assert nlink_node2.nlos_quality(-90.0, -90.0 + gap_db) == quality


@given(st.floats(-1e4, 1e4))
def test_layout_saturates_and_rounds(value: float) -> None:
    """Encoding off-grid values rounds to the nearest step and clamps at the type's limits."""
    layout = Layout((Field("angle_deg", "i16", 1, 100),))
    decoded = layout.decode(layout.encode({"angle_deg": value}))["angle_deg"]
    clamped = min(max(value, -327.68), 327.67)
    assert math.isclose(decoded, clamped, abs_tol=0.005 + 1e-9)


def test_layout_refuses_non_finite() -> None:
    layout = Layout((Field("x_m", "i32", 1, 1000),))
    with pytest.raises(ValueError, match="x_m"):
        layout.encode({"x_m": math.nan})


def test_nlink_encoder_refuses_what_the_frame_cannot_carry() -> None:
    with pytest.raises(ValueError, match="slot"):
        nlink.encode(UwbRanges(0, (AnchorRange(8, 1.0),)))
    with pytest.raises(ValueError, match="missing"):
        nlink.encode(UwbRanges(0, (AnchorRange(0, 0.0),)))


@pytest.mark.parametrize("layout", [nlink.TAG_FRAME0, dwm1001_tlv.POSITION,
                                    dwm1001_tlv.TAG_DISTANCE, dwm1001_tlv.ANCHOR_DISTANCE,
                                    nlink_node2.NODE_FRAME2, nlink_node2.NODE2_RECORD,
                                    *wit.PAYLOADS.values()])
@given(data=st.data())
def test_compiled_decoder_equals_the_reference(layout: Layout, data: st.DataObject) -> None:
    raw = data.draw(st.binary(min_size=layout.size, max_size=layout.size))
    # repr: random float32 bytes include NaNs, which never compare equal
    assert repr(layout.decode(raw)) == repr(Layout.decode(layout, raw))
