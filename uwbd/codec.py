"""Frames as JSON-ready dicts: the field names (with units) of the frame dataclasses.

Used by ``uwbd dump`` and by the decoded MCAP channels. Non-finite floats become ``null``,
so the output is strict JSON.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from drivers.frames import Frame


def frame_to_dict(frame: Frame) -> dict[str, Any]:
    """``{"type": "ImuSample", "t_ns": …, …}`` for any frame."""
    out: dict[str, Any] = {"type": type(frame).__name__}
    out.update(_plain(dataclasses.asdict(frame)))
    return out


def _plain(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
