"""The drivers' optional C accelerator (``drivers/_frames.c``, built by the package's build):
the common read of a device in one call, where the Python parser stays the reference.

Used when built, unless ``UWBD_PURE_PYTHON`` is set (uwbd's switch for all its C code: the
drivers read the variable themselves, they never import uwbd).
"""

from __future__ import annotations

import os
from types import ModuleType

PURE_PYTHON_ENV = "UWBD_PURE_PYTHON"


def _load() -> ModuleType | None:
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        from drivers import _frames  # noqa: PLC0415
    except ImportError:
        return None
    return _frames


frames = _load()
