"""Named captures in tests/data (WIRE_FORMATS.md vectors and damaged streams): what each
parser must recover, and that parsing resumes after every kind of damage."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from drivers import PARSERS, ImuSample, UwbRanges
from drivers.nlink import NlinkParser

DATA = Path(__file__).parent / "data"


def parse_file(driver: str, name: str, chunk: int = 7):
    """Feed the capture in small reads, as a serial port would deliver it."""
    data = (DATA / name).read_bytes()
    parser = PARSERS[driver]()
    frames = []
    for i in range(0, len(data), chunk):
        frames += parser.feed(data[i : i + chunk], i)
    frames += parser.flush()
    return frames, parser.stats


def test_wit_spec_examples_decode_to_the_documented_values() -> None:
    frames, stats = parse_file("wit", "wit-spec-examples.bin")
    (s,) = frames
    assert isinstance(s, ImuSample)
    assert s.acc_mps2 == (0.0, 0.0, 9.80665)  # (0, 0, +1 g)
    assert math.degrees(s.gyro_rps[2]) == pytest.approx(-10.01, abs=0.01)
    assert s.temperature_c == 25.0
    assert s.angle_deg is not None
    assert s.angle_deg[:2] == (-90.0, 45.0) and s.angle_deg[2] == pytest.approx(179.99, abs=0.01)
    assert s.mag_raw == (360, 105, -122)
    assert s.quaternion_wire == (32767 / 32768, 0.0, 0.0, 0.0)  # +1 clamped
    # the trailing time packet opens a cycle that never completes
    assert stats.dropped == 1 and stats.checksum_errors == 0


def test_wit_bad_checksum_drops_only_that_cycle() -> None:
    frames, stats = parse_file("wit", "wit-BADCK.bin")
    assert [round(f.acc_mps2[0] * 10) for f in frames] == [0, 1, 2, 4, 5]
    assert stats.checksum_errors == 1 and stats.dropped == 1
    assert stats.bytes_skipped == 11
    assert "checksum" in str(stats.recent_errors[0])


def test_wit_resumes_after_garbage_full_of_headers() -> None:
    frames, stats = parse_file("wit", "wit-GARBAGE.bin")
    assert len(frames) == 4
    assert stats.bytes_skipped == 50


def test_wit_truncated_end_is_counted_not_raised() -> None:
    frames, stats = parse_file("wit", "wit-BADEOF.bin")
    assert len(frames) == 3 and stats.bytes_skipped == 6


def test_nlink_vendor_golden_vector() -> None:
    (f,), stats = parse_file("nlink", "nlink-golden.bin")
    assert isinstance(f, UwbRanges)
    assert f.tag_id == 1 and f.device_time_ms == 71627
    assert f.tag_position_m == (2.702, -0.091, 1.0)
    assert f.tag_velocity_mps == (-0.0038, -0.0006, 0.0)
    assert [(r.anchor_id, r.range_m) for r in f.ranges] == [
        (0, 3.125), (1, 5.539), (2, 6.861), (3, 4.684)]
    assert f.tag_position_error_m == (0.11, 0.16, 2.55)
    assert stats.frames == 1 and stats.bytes_skipped == 0


def test_nlink_golden_vector_tag_imu() -> None:
    imu = NlinkParser(emit_imu=True).feed((DATA / "nlink-golden.bin").read_bytes())[1]
    assert isinstance(imu, ImuSample)
    assert imu.gyro_rps == pytest.approx((0.02767, 0.008514, -0.045762), abs=1e-6)
    assert imu.acc_mps2 == pytest.approx((0.251265, 9.74908, -0.040681), abs=1e-5)
    assert imu.angle_deg == (144.49, 97.17, -14.68)
    assert imu.quaternion_wire == pytest.approx((-0.656777, -0.125699, -0.739489, 0.0512801),
                                                abs=1e-6)


def test_nlink_bad_checksum_then_good_frame() -> None:
    frames, stats = parse_file("nlink", "nlink-BADCK.bin")
    assert len(frames) == 1 and stats.checksum_errors == 1 and stats.bytes_skipped == 128


def test_nlink_stray_headers_do_not_swallow_frames() -> None:
    frames, stats = parse_file("nlink", "nlink-STRAY55.bin")
    assert len(frames) == 2
    assert stats.bytes_skipped == 5 + 1 + 2
    assert stats.unknown_types == 2  # 55 04 (NodeFrame2, not decoded here) and 55 55


def test_dwm1001_shell_session_with_banner_echo_and_garbled_lines() -> None:
    frames, stats = parse_file("dwm1001", "dwm1001-lec-session.txt")
    assert [len(f.ranges) for f in frames] == [4, 3, 3, 0, 0]
    first = frames[0]
    assert (first.ranges[0].anchor_id, first.ranges[0].range_m) == (0x022E, 3.44)
    assert first.ranges[0].anchor_position_m == (7.94, 8.03, 0.0)
    assert (first.tag_position_m, first.quality) == ((6.95, 5.37, -1.97), 52.0)
    assert frames[1].tag_position_m is None  # no POS block: position not computed
    assert frames[2].quality == 50.0  # CR-only line ending
    assert (frames[3].tag_position_m, frames[3].quality) == ((2.57, 2.0, 1.67), 97.0)  # lePOS
    assert stats.malformed == 2  # the truncated-and-repeated AN3 block; DIST,2 with one block


def test_dwm1001_tlv_spec_example() -> None:
    (f,), stats = parse_file("dwm1001-tlv", "dwm1001-tlv-spec-example.bin")
    assert f.tag_position_m == (1.5, -0.25, 1.0) and f.quality == 87.0
    assert [(r.anchor_id, r.range_m, r.anchor_position_m) for r in f.ranges] == [
        (0x1151, 6.44, (5.0, 8.0, 2.25)), (0x0CA8, 6.5, (0.0, 8.0, 2.25))]
    assert stats.bytes_skipped == 0


def test_dwm1001_tlv_error_replies_and_truncation() -> None:
    frames, stats = parse_file("dwm1001-tlv", "dwm1001-tlv-ERROR.bin")
    assert len(frames) == 1
    assert stats.device_errors == 2  # '@\x01\x01' and 'busy'
    assert "busy" in str(stats.recent_errors[-1])
    assert stats.bytes_skipped == 3 + 3 + 20
