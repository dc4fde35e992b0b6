"""Regenerate the named byte captures in this folder: ``python tests/data/make_captures.py``.

Each file is a device stream with one named kind of damage; the tests state what a parser
must recover from it. Vectors quoted from WIRE_FORMATS.md are copied byte for byte.
"""

from __future__ import annotations

from pathlib import Path

from drivers import wit
from drivers.frames import ImuSample

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


if __name__ == "__main__":
    main()
