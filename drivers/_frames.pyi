"""Types of the drivers' C accelerator (_frames.c); nlink.py holds the reference."""

from typing import Any

def tag_frame0(data: bytes, t_ns: int, parts: tuple[Any, ...]) -> Any: ...
