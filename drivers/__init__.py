"""Serial device protocols for uwbd: sans-I/O parsers and encoders, and a pty emulator.

``PARSERS`` maps a driver name, as used in configs and on the command line, to a factory of
its incremental parser; ``ENCODERS`` to its encoder. Never imports ``uwbd``.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers import dwm1001, dwm1001_tlv, nlink, wit
from drivers.base import FrameError, Parser, ParserStats
from drivers.frames import AnchorRange, Frame, ImuSample, UwbRanges

PARSERS: dict[str, Callable[[], Parser]] = {
    "wit": wit.WitParser,
    "dwm1001": dwm1001.Dwm1001ShellParser,
    "dwm1001-tlv": dwm1001_tlv.Dwm1001TlvParser,
    "nlink": nlink.NlinkParser,
}

__all__ = [
    "PARSERS", "AnchorRange", "Frame", "FrameError", "ImuSample", "Parser", "ParserStats",
    "UwbRanges",
]
