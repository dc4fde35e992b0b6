"""Serial device protocols for uwbd: sans-I/O parsers and encoders, and a pty emulator.

``PARSERS`` maps a driver name, as used in configs and on the command line, to a factory of
its incremental parser (``drivers.emulator.ENCODERS`` maps it to its encoder). Never imports
``uwbd``.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers import dwm1001, dwm1001_tlv, nlink, nlink_node2, trek1000, wit
from drivers.base import FrameError, Parser, ParserStats
from drivers.frames import AnchorPair, AnchorRange, AnchorRanges, Frame, ImuSample, UwbRanges

PARSERS: dict[str, Callable[[], Parser]] = {
    "wit": wit.new_parser,
    "dwm1001": dwm1001.Dwm1001ShellParser,
    "dwm1001-tlv": dwm1001_tlv.Dwm1001TlvParser,
    "nlink": nlink.NlinkParser,
    "nlink-node2": nlink_node2.NlinkNode2Parser,
    "trek1000": trek1000.Trek1000Parser,
    "trek1000-raw": trek1000.Trek1000RawParser,
}

__all__ = [
    "PARSERS", "AnchorPair", "AnchorRange", "AnchorRanges", "Frame", "FrameError", "ImuSample",
    "Parser",
    "ParserStats", "UwbRanges",
]
