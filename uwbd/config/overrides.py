"""Writing configs: :func:`apply_overrides` sets ``section.key=value`` items from the
command line (``--set``) and writes the document used; :func:`to_toml` writes one for given
settings (what ``uwbd simulate``, ``import`` and the demo store), both through
:func:`write_toml`."""

from __future__ import annotations

import dataclasses
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import tomli_w

from drivers import PARSERS
from uwbd.config.checks import Report, mounting_rotation
from uwbd.config.model import ConfigError, SourceConfig
from uwbd.config.schema import SECTIONS, SOURCE_SPEC, TABLES, VEC3, anchor_id
from uwbd.config.spelling import known, one_line, show, type_name

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def apply_overrides(text: str, overrides: Sequence[str], where: str = "<config>") -> str:
    """``text`` with each ``section.key=value`` of ``overrides`` set, as a TOML document.

    The value is TOML (``0.2``, ``false``, ``"loose"``, ``[1, 2, 0.5]``), or a bare word taken
    as a string (``loose``, ``/dev/ttyUSB1``). ``sources.<name>.<key>`` (or
    ``sources[<index>].<key>``) sets a key of a ``[[sources]]`` entry. A problem with an
    override is a :class:`ConfigError` naming it (``--set fusion.zupt=maybe: expected true
    or false, got "maybe" (a string)``); the rest of the file is checked by ``parse``.
    Without overrides, ``text`` comes back as it is (comments and all).
    """
    if not overrides:
        return text
    doc = toml_document(text, where)
    for item in overrides:
        _apply_override(doc, item, where)
    said = " ".join(f"--set {item}" for item in overrides)
    return f"# {one_line(where)} with {one_line(said)}\n" + write_toml(doc)


def toml_document(text: str, where: str) -> dict[str, Any]:
    """``text`` read as TOML; what is not TOML, or is nested past any config (a recursion
    the parser cannot finish), is a :class:`ConfigError` naming ``where``."""
    try:
        doc: dict[str, Any] = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{where}: {err}") from err
    except RecursionError as err:
        raise ConfigError(f"{where}: arrays or tables nested too deeply to be a config") from err
    return doc


def _apply_override(doc: dict[str, Any], item: str, where: str) -> None:
    def fail(what: str) -> ConfigError:
        return ConfigError(f"--set {one_line(item)}: {what}")

    path, equals, raw = item.partition("=")
    path, raw = path.strip(), raw.strip()
    if not equals or not path:
        raise fail("expected section.key=value (fusion.zupt=false)")
    value = _override_value(raw, fail)
    source = re.fullmatch(r"sources(?:\[(\d+)\]|\.(.+))\.([^.]+)", path)
    if source is not None:
        index, name, key = source.groups()
        table = _override_source(doc, int(index) if index is not None else None, name, fail,
                                 where)
        spec = SOURCE_SPEC.get(key)
        if spec is None:
            raise fail(f"unknown key {key!r}" + known(key, list(SOURCE_SPEC)))
        problem = spec.problem(value)
        if problem is None and key == "driver" and value not in PARSERS:
            problem = f"unknown driver {show(value)} (known: {', '.join(PARSERS)})"
        if problem is not None:
            raise fail(problem)
        table[key] = value
        return
    section, dot, key = path.partition(".")
    key = key.strip('"')
    if section == "sources":
        raise fail("expected sources.<name>.<key> or sources[<index>].<key>")
    if section not in SECTIONS:
        raise fail(f"unknown section {section!r}" + known(section, SECTIONS))
    if not dot or not key:
        raise fail(f"expected {section}.<key>=value")
    table = doc.setdefault(section, {})
    if not isinstance(table, dict):
        raise fail(f"{section} in {where} is not a table")
    if section == "anchors":
        key, value = _anchor_override(table, key, value, fail)
    else:
        spec = TABLES[section].get(key)
        if spec is None:
            raise fail(f"unknown key {section}.{key}" + known(key, sorted(TABLES[section])))
        problem = spec.problem(value)
        if problem is None and key == "mounting":
            problem = _rotation_problem(value)
        if problem is not None:
            raise fail(problem)
    table[key] = value


def _anchor_override(table: dict[str, Any], key: str, value: Any,
                     fail: Callable[[str], ConfigError]) -> tuple[str, Any]:
    """``anchors.<id>=[x, y, z]`` (an orientation the anchor has stays), ``anchors.<id>={
    position_m = …, orientation_xyzw = … }``, or ``anchors.<id>.position_m`` /
    ``.orientation_xyzw`` alone: the entry's key and its new value (``parse`` checks the
    numbers and names what is wrong)."""
    ident, _, field = key.partition(".")
    found = anchor_id(ident.strip('"'))
    if found is None:
        raise fail("an anchor id is an integer of 0 or more (\"3\", \"0x1151\")")
    old: Any = None
    for other in [k for k in table if anchor_id(k) == found]:
        old = table.pop(other)  # the same anchor, spelt otherwise ("0x3" for "3")
    entry = dict(old) if isinstance(old, dict) else (
        {"position_m": old} if old is not None else {})
    fields = ("position_m", "orientation_xyzw")
    if field:
        if field not in fields:
            raise fail("an anchor takes position_m and orientation_xyzw" + known(field, fields))
        return ident, {**entry, field: value}
    if isinstance(value, dict):
        return ident, value
    if not VEC3.ok(value):
        raise fail(f"expected {VEC3.what}, got {show(value)} ({type_name(value)})")
    return ident, ({**entry, "position_m": value} if "orientation_xyzw" in entry else value)


def _override_source(doc: dict[str, Any], index: int | None, name: str | None,
                     fail: Callable[[str], ConfigError], where: str) -> dict[str, Any]:
    entries = doc.get("sources", [])
    if not isinstance(entries, list):
        raise fail(f"sources in {where} is not an array of tables")
    tables = [s for s in entries if isinstance(s, dict)]
    if index is not None:
        if not 0 <= index < len(entries) or not isinstance(entries[index], dict):
            raise fail(f"no sources[{index}] ({len(entries)} sources)")
        found: dict[str, Any] = entries[index]
        return found
    named = [s for s in tables if s.get("name") == name]
    if not named:
        names = [str(s.get("name")) for s in tables]
        raise fail(f"no source named {name!r}" + known(name or "", names, "sources"))
    return named[0]


def _override_value(raw: str, fail: Callable[[str], ConfigError]) -> Any:
    if not raw:
        raise fail("no value after =")
    try:
        return tomllib.loads(f"value = {raw}")["value"]
    except RecursionError as err:
        raise fail("nested too deeply to be a value") from err
    except tomllib.TOMLDecodeError as err:
        if re.fullmatch(r"[^\s\"'\[\]{}=#,]+", raw):
            return raw  # a bare word: a string
        said = re.sub(r"\s*\(at (line \d+, column \d+|end of document)\)", "", str(err))
        raise fail(f"not a TOML value ({said}); quote a string: \"...\"") from err


def _rotation_problem(rows: list[list[float]]) -> str | None:
    r = Report("")
    mounting_rotation(r, rows)
    return r.errors[0].split(": ", 2)[2] if r.errors else None


def to_toml(sources: Sequence[SourceConfig], anchors_m: Mapping[int, Sequence[float]],
            mounting: Sequence[Sequence[float]], lever_arm_m: Sequence[float],
            fusion: Mapping[str, Any] | None = None,
            imu: Mapping[str, float] | None = None,
            anchor_orientations_xyzw: Mapping[int, Sequence[float]] | None = None) -> str:
    """A config file for these settings (what ``uwbd simulate`` and ``import`` store), its
    ``[fusion]`` table last; an anchor with an orientation in the table form."""
    def vec(v: Sequence[float]) -> list[float]:
        return [float(x) for x in v]

    def anchor(k: int, v: Sequence[float]) -> Any:
        q = (anchor_orientations_xyzw or {}).get(k)
        return vec(v) if q is None else {"position_m": vec(v), "orientation_xyzw": vec(q)}

    doc: dict[str, Any] = {"sources": [dataclasses.asdict(s) for s in sources]} if sources else {}
    doc["anchors"] = {str(k): anchor(k, v) for k, v in sorted(anchors_m.items())}
    doc["imu"] = {"mounting": [vec(r) for r in mounting], "lever_arm_m": vec(lever_arm_m),
                  **{k: float(v) for k, v in (imu or {}).items()}}
    doc["fusion"] = dict(fusion or {})
    return write_toml(doc)


def write_toml(doc: Mapping[str, Mapping[str, Any] | Sequence[Mapping[str, Any]]]) -> str:
    """A config document as a person writes one: a ``[section]`` per table, ``[[sources]]``
    blocks, arrays on one line (tomli-w alone puts each item on a line of its own, 17 lines
    for a mounting matrix); keys and scalar values are spelt by tomli-w."""
    def key(k: str) -> str:
        return tomli_w.dumps({k: 0}).rsplit(" = ", 1)[0]

    def value(v: Any) -> str:
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, Mapping):  # an inline table ({ 1 = -0.12, 2 = 0.02 })
            return "{ " + ", ".join(f"{key(str(k))} = {value(x)}" for k, x in v.items()) + " }"
        return tomli_w.dumps({"v": v})[len("v = "):].rstrip("\n")

    lines: list[str] = []
    for name, body in doc.items():
        tables = [body] if isinstance(body, Mapping) else list(body)
        header = f"[{key(name)}]" if isinstance(body, Mapping) else f"[[{key(name)}]]"
        for table in tables:
            lines += [header, *(f"{key(k)} = {value(v)}" for k, v in table.items()), ""]
    return "\n".join(lines)
