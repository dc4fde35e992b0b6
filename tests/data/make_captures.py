"""Regenerate the named byte captures in this folder: ``python tests/data/make_captures.py``.

Each file is a device stream with one named kind of damage; the tests state what a parser
must recover from it. Vectors quoted from docs/wire-formats.md are copied byte for byte.
"""

from __future__ import annotations

from pathlib import Path

from drivers import nlink_node2, trek1000, wit
from drivers.frames import AnchorRange, ImuSample, UwbRanges

HERE = Path(__file__).parent

WIT_SPEC_EXAMPLES = bytes.fromhex(
    "55510000000000 08C4097B" "55520000 00005CFFC409CF" "555300C00020FE7F230129"
    "5554680169 0086FFC409CD" "5559FF7F000000000000 2C" "55501805060708097B005B".replace(" ", "")
    .replace(" ", ""))
NLINK_GOLDEN = bytes.fromhex(
    "550101028e0a00a5ffffe80300daffff faffff000000350c00a31500cd1a004c"
    "12000000000000000000000000 0027ace23ca27d0b3cd2703bbdcfa5803e3efc"
    "1b411fa126bd265d5741bd8057413f6357417138f52544fa8a2228bf5ab700be"
    "204f3dbf1c0b523df4263d400cae0000cb170100f00b10ff54131d480000bcfd".replace(" ", ""))
TLV_SPEC_EXAMPLE = bytes.fromhex(
    "400100 410DDC05000006FFFFFFE803000057 492902"
    "5111281900006488130000401F0000CA08000064"
    "A80C6419000064000000 00401F0000CA08000064".replace(" ", ""))

# nooploop-dev/nlink_parser test/test_nlink_parser.cpp, the NodeFrame2 case (docs/wire-formats.md)
NODE2_GOLDEN = bytes.fromhex(
    "5504ac000201ba661d000609ffde0a00dfffffe80300faffff1a0000000000c012000000000000"
    "0027ace23c56ed1c3cd2703bbd3257663e3bcb1b41937061bd25b26b41a1226c41dada6b416d23"
    "e92370dddbf7303f5fd6313fba811e3e4769e2bd919b4040c52300004040 5cd51c0000001d006d"
    "130401006b0c00b19fa6661d00164501 01ac1500b4a1a6661d00d3010102481a00ca9fa6661d00"
    "38ba01032b1200c6a0a6661d00644025".replace(" ", ""))
# docs/wire-formats.md: the example lines of the Decawave PC source, byte for byte
TREK_SPEC_EXAMPLES = (
    b"mc 0f 00000663 000005a3 00000512 000004cb 095f c1 00024c24 a0:0\r\n"
    b"mr 0f 000005a4 000004c8 00000436 000003f9 0958 c0 40424042 a0:0\r\n"
    b"ma 07 00000000 0000085c 00000659 000006b7 095b 26 00024bed a0:0\r\n")


def _trek_session() -> bytes:
    """A tag's stream with every kind of trouble §4.6-4.7 names, one per line."""
    def mc(mask: int, ranges: tuple[int, int, int, int], trailer: bytes = b"t0:0") -> bytes:
        return (b"mc %02x %08x %08x %08x %08x 0001 02 00000003 " % (
            mask, *(r & 0xFFFFFFFF for r in ranges)) + trailer)
    return b"".join([
        b"n" + trek1000.VERSION + bytes((trek1000.S1_CONFIG,)) + b"\r\n",  # deca$ reply
        mc(0x0F, (1000, 2000, 3000, 4000)) + b"\r\n",
        mc(0x05, (-20, 0, 1500, 0)) + b"\r\n",  # ffffffec = -20 mm; A1, A3 not valid
        b"me 0000 0001 0002 0003 0004 0005 0006 0007 0008 0009\r\n",  # event counters
        b"mc 00 00000001 00000002 00000003 00000004 00000005 00000006 00000007 00000008"
        b" 0001 02 00000003 t0:0\r\n",  # a clone's 8-anchor line: malformed
        mc(0x1F, (1, 2, 3, 4)) + b"\r\n",  # a mask bit above A3: malformed
        b"\x7f\xfe\x00garbage" + mc(0x03, (500, 600, 0, 0)) + b"\r\n",  # garbage glued before
        mc(0x0F, (1, 2, 3, 4))[:40] + b"\r\n",  # a truncated line: malformed
        mc(0x08, (0, 0, 0, 7000), b"t12:3") + b"\r",  # two-digit tag id; CR only
        mc(0x01, (900, 0, 0, 0), b"l1:0") + b"\n",  # a listener; LF only
        b"ma 0e 00000000 00001000 00002000 00003000 0001 02 00000003 a1:0\r\n",  # not from A0
        b"ma 0e 00000000 00001000 00002000 00003000 0001 02 00000003 a0:0\r\n",
    ])


def _node2(k: int) -> bytes:
    return nlink_node2.encode(UwbRanges(0, tuple(
        AnchorRange(a, 1.0 + a + 0.1 * k, fp_rssi_dbm=-85.0, rx_rssi_dbm=-80.0)
        for a in range(4)), (1.0, 2.0, 0.5), tag_id=1, device_time_ms=1000 + k))


def _cycle(k: int) -> bytes:
    return wit.encode(ImuSample(0, (0.1 * k, 0.0, 9.80665), (0.0, 0.01 * k, 0.0), 25.0,
                                angle_deg=(0.0, 0.0, float(k))))


def main() -> None:
    (HERE / "wit-spec-examples.bin").write_bytes(WIT_SPEC_EXAMPLES)
    bad = bytearray(_cycle(3))
    bad[wit.PACKET_LEN + 5] ^= 0x01  # the gyro packet of this cycle fails its checksum
    (HERE / "wit-BADCK.bin").write_bytes(b"".join(_cycle(k) for k in range(3)) + bad
                                         + _cycle(4) + _cycle(5))
    junk = bytes((0x55, 0x51, 0x00, 0x55, 0x55, 0x53, 0x17, 0xFF, 0x00, 0x55) * 5)
    (HERE / "wit-GARBAGE.bin").write_bytes(junk + b"".join(_cycle(k) for k in range(4)))
    (HERE / "wit-BADEOF.bin").write_bytes(b"".join(_cycle(k) for k in range(3)) + _cycle(3)[:6])
    (HERE / "nlink-golden.bin").write_bytes(NLINK_GOLDEN)
    broken = bytearray(NLINK_GOLDEN)
    broken[30] ^= 0xFF
    (HERE / "nlink-BADCK.bin").write_bytes(bytes(broken) + NLINK_GOLDEN)
    (HERE / "nlink-STRAY55.bin").write_bytes(b"\x55\x01\x55\x04\x00" + NLINK_GOLDEN
                                             + b"\x55" + NLINK_GOLDEN + b"\x55\x01")
    (HERE / "dwm1001-tlv-ERROR.bin").write_bytes(
        b"@\x01\x01" + TLV_SPEC_EXAMPLE + b"\x40\x01\x04" + TLV_SPEC_EXAMPLE[:20])
    (HERE / "dwm1001-tlv-spec-example.bin").write_bytes(TLV_SPEC_EXAMPLE)
    # the spec example cut short by 1, 2, 4, 5, 20 and 40 bytes, each followed by a good one
    (HERE / "dwm1001-tlv-TRUNCATED.bin").write_bytes(b"".join(
        TLV_SPEC_EXAMPLE[:-cut] + TLV_SPEC_EXAMPLE for cut in (1, 2, 4, 5, 20, 40)))
    (HERE / "nlink-node2-golden.bin").write_bytes(NODE2_GOLDEN)
    bad = bytearray(_node2(1))
    bad[50] ^= 0x10
    (HERE / "nlink-node2-DAMAGED.bin").write_bytes(
        _node2(0) + bytes(bad) + _node2(2)  # a checksum error between good frames
        + b"\x55\x04\xff\x00"  # a length no node count fits
        + NLINK_GOLDEN  # a TagFrame0: not this driver's frame
        + _node2(3)[:100] + _node2(4)  # a truncated frame, then a good one
        + b"\x55\x04\xac")  # a header cut by the end of the capture
    (HERE / "trek1000-spec-examples.txt").write_bytes(TREK_SPEC_EXAMPLES)
    (HERE / "trek1000-session.txt").write_bytes(_trek_session())


if __name__ == "__main__":
    main()
