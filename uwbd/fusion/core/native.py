"""Which implementation of the filter's hot algebra runs: the C core (``_core.c``, built by
the package's build) or the pure-Python reference in :mod:`.eskf`.

The C core is used when it was built and imports, unless ``UWBD_PURE_PYTHON=1`` is set in
the environment (a fallback to rule the extension out, and the oracle the tests compare it
against). :func:`pure_python` switches it off for the filters made inside a ``with`` block.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from types import ModuleType

Core = ModuleType | None  # the C core's module, or None: the pure-Python reference

PURE_PYTHON_ENV = "UWBD_PURE_PYTHON"


def _load() -> tuple[ModuleType | None, str]:
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None, f"pure Python ({PURE_PYTHON_ENV} is set)"
    try:
        from uwbd.fusion.core import _core  # noqa: PLC0415
    except ImportError as err:
        return None, f"pure Python (the C core is not built: {err})"
    return _core, "C core"


core, implementation = _load()


@contextlib.contextmanager
def pure_python() -> Iterator[None]:
    """Filters made inside the block run the pure-Python reference."""
    global core  # noqa: PLW0603 - the switch is this module's one job
    saved, core = core, None
    try:
        yield
    finally:
        core = saved
