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
    wit_streams,
)

from drivers import PARSERS, dwm1001, dwm1001_tlv, nlink, wit
from drivers.frames import AnchorRange, ImuSample, UwbRanges
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
                                    dwm1001_tlv.TAG_DISTANCE, *wit.PAYLOADS.values()])
@given(data=st.data())
def test_compiled_decoder_equals_the_reference(layout: Layout, data: st.DataObject) -> None:
    raw = data.draw(st.binary(min_size=layout.size, max_size=layout.size))
    # repr: random float32 bytes include NaNs, which never compare equal
    assert repr(layout.decode(raw)) == repr(Layout.decode(layout, raw))
