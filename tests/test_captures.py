"""Named captures in tests/data (docs/wire-formats.md vectors and damaged streams): what each
parser must recover, and that parsing resumes after every kind of damage."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from drivers import PARSERS, AnchorPair, AnchorRanges, ImuSample, UwbRanges, nlink_node2, trek1000
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


def test_dwm1001_tlv_truncated_responses_do_not_swallow_the_next() -> None:
    """Each cut-short response (1 to 40 bytes lost) is followed by a good one: every good one
    arrives. Cut by 1-2 bytes, the short one is complete with the next one's first bytes and
    leaves the parser before that shows (its ranges intact); then the parser goes back."""
    frames, stats = parse_file("dwm1001-tlv", "dwm1001-tlv-TRUNCATED.bin")
    (good,), _ = parse_file("dwm1001-tlv", "dwm1001-tlv-spec-example.bin", chunk=1000)
    at0 = [dataclasses.replace(f, t_ns=0) for f in frames]
    # the 6 good ones, and the two cut by 1 and 2 bytes: the first lost only its last
    # anchor's position qf, which no frame carries; the second also z's top byte, so that
    # anchor is 1073 km up (the filter refuses such a position; a configured one wins)
    assert len(at0) == 8 and at0.count(good) == 7
    (odd,) = [f for f in at0 if f != good]
    assert odd.ranges[-1].anchor_position_m is not None
    assert odd.ranges[-1].anchor_position_m[2] > 1e6
    assert stats.malformed == 6
    assert all("cut short" in str(e) for e in stats.recent_errors)
    # read whole, the straddling starts are seen before anything leaves: only the good ones
    parser = PARSERS["dwm1001-tlv"]()
    whole = parser.feed((DATA / "dwm1001-tlv-TRUNCATED.bin").read_bytes()) + parser.flush()
    assert whole == [good] * 6 and parser.stats.malformed == 6


def test_nlink_node2_vendor_golden_vector() -> None:
    (f,), stats = parse_file("nlink-node2", "nlink-node2-golden.bin")
    assert isinstance(f, UwbRanges)
    assert f.tag_id == 1 and f.device_time_ms == 1926842
    assert f.tag_position_m == (2.782, -0.033, 1.0)
    assert f.tag_velocity_mps == (-0.0006, 0.0026, 0.0)
    assert f.tag_position_error_m == (0.06, 0.09, 2.55)
    assert [(r.anchor_id, r.range_m, r.fp_rssi_dbm, r.rx_rssi_dbm) for r in f.ranges] == [
        (0, 3.179, -88.5, -79.5), (1, 5.548, -90.0, -80.5), (2, 6.728, -101.0, -79.5),
        (3, 4.651, -99.0, -80.0)]
    # rx - fp = 9, 9.5, 21.5, 19 dB: past the 6 dB of a direct path, two of them far past
    assert [r.quality for r in f.ranges] == [70.0, 65.0, 0.0, 0.0]
    assert stats.frames == 1 and stats.bytes_skipped == 0


def test_nlink_node2_golden_vector_fields_and_tag_imu() -> None:
    data = (DATA / "nlink-node2-golden.bin").read_bytes()
    fixed = nlink_node2.NODE_FRAME2.decode(data)
    assert (fixed["role"], fixed["id"], fixed["frame_length"]) == (2, 1, 172)
    assert fixed["local_time_ms"] == 9157 and fixed["voltage_v"] == 4.973
    assert fixed["valid_node_count"] == 4
    record = nlink_node2.NODE2_RECORD.decode(data, nlink_node2.FIXED_LEN)
    assert (record["role"], record["system_time_ms"]) == (1, 1926822)  # an anchor
    # the one table encodes what it decodes, reserved bytes included
    assert bytes(nlink_node2.NODE_FRAME2.encode(fixed)) == data[:nlink_node2.FIXED_LEN]
    _, imu = nlink_node2.NlinkNode2Parser(emit_imu=True).feed(data)
    assert isinstance(imu, ImuSample)
    assert imu.gyro_rps == pytest.approx((0.02767, 0.00958, -0.04576), abs=1e-5)
    assert imu.acc_mps2 == pytest.approx((0.224942, 9.73712, -0.05504), abs=1e-5)
    assert imu.angle_deg == (90.69, 91.93, -88.48)
    assert imu.quaternion_wire == pytest.approx((0.691282, 0.694677, 0.154792, -0.110552),
                                                abs=1e-6)


def test_nlink_node2_damaged_stream() -> None:
    frames, stats = parse_file("nlink-node2", "nlink-node2-DAMAGED.bin")
    # 0, 2 and 4 arrive: 1 fails its checksum, 3 was cut short and does not swallow 4
    assert [f.device_time_ms for f in frames] == [1000, 1002, 1004]
    assert stats.checksum_errors == 1
    assert stats.malformed == 2  # the impossible length; 3's length against 4's node count
    assert stats.unknown_types == 1  # the TagFrame0 (driver nlink reads those)
    assert stats.bytes_in - stats.bytes_skipped == 3 * 172


def test_nlink_node2_ignores_tag_frames_and_nlink_ignores_node_frames() -> None:
    """One port may carry both kinds; each driver takes its own."""
    data = b"".join((DATA / n).read_bytes() for n in ("nlink-golden.bin",
                                                      "nlink-node2-golden.bin"))
    (tag,), _ = parse_file("nlink", "nlink-golden.bin")
    (node,), _ = parse_file("nlink-node2", "nlink-node2-golden.bin")
    assert PARSERS["nlink"]().feed(data, 77) == [dataclasses.replace(tag, t_ns=77)]
    assert PARSERS["nlink-node2"]().feed(data, 77) == [dataclasses.replace(node, t_ns=77)]


def test_trek1000_spec_examples() -> None:
    (mc, ma), stats = parse_file("trek1000", "trek1000-spec-examples.txt")
    assert isinstance(mc, UwbRanges) and isinstance(ma, AnchorRanges)
    assert [(r.anchor_id, r.range_m) for r in mc.ranges] == [
        (0, 1.635), (1, 1.443), (2, 1.298), (3, 1.227)]  # 0x663 mm ...
    assert (mc.tag_id, mc.device_time_ms, mc.quality) == (0, 0x24C24, None)
    # ma 07: bit 0's field is unused, bits 1 and 2 are A0-A1 and A0-A2; A1-A2 is not valid
    assert ma.pairs == (AnchorPair(0, 1, 2.140), AnchorPair(0, 2, 1.625))
    assert ma.device_time_ms == 0x24BED
    assert stats.malformed == 0 and stats.bytes_skipped == 65  # the mr line
    (mr, ma_raw), _ = parse_file("trek1000-raw", "trek1000-spec-examples.txt")
    assert [(r.anchor_id, r.range_m) for r in mr.ranges] == [
        (0, 1.444), (1, 1.224), (2, 1.078), (3, 1.017)]
    assert mr.device_time_ms is None  # field 9 of mr is the antenna delays
    assert ma_raw == ma


def test_trek1000_encoder_reproduces_the_spec_lines_byte_for_byte() -> None:
    lines = (DATA / "trek1000-spec-examples.txt").read_bytes().splitlines(keepends=True)
    assert [len(x) for x in lines] == [65, 65, 65]
    (mc, ma), _ = parse_file("trek1000", "trek1000-spec-examples.txt")
    assert trek1000.encode(mc, False, 0x095F, 0xC1, reporter="a") == lines[0]
    # bits 0 and 3 of the spec's ma mask are clear or carry nothing: the encoder writes 0
    # for A1-A2 (not valid in it) and leaves bit 0 clear
    assert trek1000.encode(ma, count=0x095B, seq=0x26) == lines[2].replace(
        b"ma 07", b"ma 06").replace(b"000006b7", b"00000000")


def test_trek1000_session_with_handshake_garbage_and_clone_lines() -> None:
    frames, stats = parse_file("trek1000", "trek1000-session.txt")
    uwb = [f for f in frames if isinstance(f, UwbRanges)]
    assert [[(r.anchor_id, r.range_m) for r in f.ranges] for f in uwb] == [
        [(0, 1.0), (1, 2.0), (2, 3.0), (3, 4.0)],
        [(0, -0.02), (2, 1.5)],  # ffffffec = -20 mm is kept (gating rejects it); A1, A3 clear
        [(0, 0.5), (1, 0.6)],  # garbage glued before the line
        [(3, 7.0)],  # two-digit tag id, CR-only line end
        [(0, 0.9)],  # a listener's line, LF-only
    ]
    assert [f.tag_id for f in uwb] == [0, 0, 0, 12, 1]
    (ma,) = [f for f in frames if isinstance(f, AnchorRanges)]
    assert ma.pairs == (AnchorPair(0, 1, 4.096), AnchorPair(0, 2, 8.192), AnchorPair(1, 2, 12.288))
    # the 8-range clone line, the mask above A3, the truncated line, the ma not from A0
    assert stats.malformed == 4
    assert stats.device_errors == stats.checksum_errors == 0


def test_trek1000_anchor_ranges_can_be_left_out() -> None:
    data = (DATA / "trek1000-spec-examples.txt").read_bytes()
    parser = trek1000.Trek1000Parser(anchor_ranges=False)
    assert [type(f) for f in parser.feed(data) + parser.flush()] == [UwbRanges]
    assert parser.stats.bytes_skipped == 2 * 65 and parser.stats.malformed == 0
