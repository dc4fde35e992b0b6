"""How the config's messages spell what they are about: a key or a value as the TOML would
(on one line, cut short), a value's type, and the names known with the closest suggested."""

from __future__ import annotations

import datetime
import difflib
import math
import re
from collections.abc import Sequence
from typing import Any

_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}


def _string(s: str) -> str:
    return '"' + "".join(_ESCAPES.get(c, f"\\u{ord(c):04x}" if ord(c) < 0x20 or c == "\x7f"
                                      else c) for c in s) + '"'


def toml_key(k: str) -> str:
    """A key as the TOML spells it: bare, or quoted (``anchors."a b"``)."""
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _string(k)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else
                                                 "inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return ("{ " + ", ".join(f"{toml_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
                if v else "{}")
    if isinstance(v, (datetime.date, datetime.time)):  # datetime is a date
        return v.isoformat()
    return repr(v)


def show(v: Any) -> str:
    """A value as the TOML would spell it on one line, cut short."""
    text = _value(v)
    return text if len(text) <= 60 else text[:57] + "..."


def type_name(v: Any) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a float"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return f"an array of {len(v)}"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, datetime.datetime):
        return "a date-time"
    if isinstance(v, datetime.date):
        return "a date"
    if isinstance(v, datetime.time):
        return "a time"
    return type(v).__name__


def maybe(word: str, known: Sequence[str]) -> str:
    """`` (did you mean X?)`` for the closest of ``known``, or nothing."""
    close = difflib.get_close_matches(word, list(known), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def known(word: str, names: Sequence[str], label: str = "known") -> str:
    """`` (did you mean X? known: A, B, X)``, the question only when one is close."""
    close = difflib.get_close_matches(word, list(names), n=1)
    listed = f"{label}: {', '.join(names) or 'none'}"
    return f" (did you mean {close[0]}? {listed})" if close else f" ({listed})"


def one_line(s: str) -> str:
    return "".join(c if c >= " " and c != "\x7f" else f"\\u{ord(c):04x}" for c in s)
