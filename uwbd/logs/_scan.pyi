"""Types of the log reader's per-message loops in C (_scan.c); scan.py and mcaplog.py hold
the reference each function translates."""

from collections.abc import Callable
from typing import Any

def chunk_messages(data: bytes, pos: int) -> tuple[list[tuple[int, int, bytes]], int]: ...
def log_messages(records: list[tuple[int, int, bytes]], topics: dict[int, str],
                 raw_channels: set[int], decode_raw: Callable[[bytes], bytes],
                 message_type: type[Any], out: list[Any]) -> None: ...
