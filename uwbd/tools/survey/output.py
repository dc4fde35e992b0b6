"""A survey written out: the ``[anchors]`` table, a TOML snippet, a config with them."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

from uwbd.config import ConfigError, parse
from uwbd.config.overrides import write_toml
from uwbd.config.schema import anchor_id
from uwbd.tools.survey.model import Survey, SurveyError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def table(result: Survey) -> str:
    """The positions, their 1-σ and the change from the config, one line per anchor."""
    lines = [f"{'anchor':>6} {'x m':>9} {'y m':>9} {'z m':>8}  {'σx':>6} {'σy':>6} {'σz':>6}"
             f"  {'Δx':>7} {'Δy':>7} {'Δz':>7} {'|Δ|':>6}"
             + ("  offset m" if any(e.range_offset_m is not None
                                     for e in result.anchors.values()) else "")]
    for a, e in sorted(result.anchors.items()):
        x, y, zz = e.position_m
        sx, sy, sz = e.sigma_m
        line = f"{a:>6} {x:9.3f} {y:9.3f} {zz:8.3f}  {sx:6.3f} {sy:6.3f} {sz:6.3f}"
        d = e.change_m
        line += (f"  {d[0]:+7.3f} {d[1]:+7.3f} {d[2]:+7.3f} {math.hypot(*d):6.3f}"
                 if d is not None else f"  {'(not in the config)':>30}")
        if e.range_offset_m is not None and e.range_offset_sigma_m is not None:
            line += f"  {e.range_offset_m:+.3f} ± {e.range_offset_sigma_m:.3f}"
        if not e.surveyed:
            line += "  (no ranges: as configured)"
        lines.append(line)
    return "\n".join(lines)


def anchors_document(result: Survey, header: str,
                     orientations_xyzw: dict[int, list[float]] | None = None) -> str:
    """A TOML file holding the surveyed ``[anchors]`` table (mm), an anchor's orientation
    (``orientations_xyzw``, the config's) kept, turned with the frame; checked by
    :func:`uwbd.config.parse`."""
    kept = orientations_xyzw or {}

    def entry(a: int, p: Sequence[float]) -> Any:
        surveyed = [round(v, 3) for v in p]
        q = kept.get(a)
        return surveyed if q is None else {
            "position_m": surveyed, "orientation_xyzw": turned_xyzw(q, result.frame_turn_deg)}

    doc = {"anchors": {str(a): entry(a, p) for a, p in result.positions().items()}}
    text = _comment(header) + write_toml(doc)
    _check(text, "the anchors file")
    return text


def orientations_of(config_text: str) -> dict[int, list[float]]:
    """The anchors' orientations (x, y, z, w) a config's ``[anchors]`` gives (table form)."""
    table = tomllib.loads(config_text).get("anchors", {})
    return {found: entry["orientation_xyzw"] for key, entry in table.items()
            if isinstance(entry, dict) and "orientation_xyzw" in entry
            and (found := anchor_id(key)) is not None}


def with_anchors(config_text: str, result: Survey, header: str, where: str) -> str:
    """``config_text`` with its ``[anchors]`` replaced by the surveyed ones (each keeping the
    key it was spelt with, and its orientation where it has one; anchors the survey did not
    see kept), as a TOML document that
    :func:`uwbd.config.parse` accepts. Comments are not kept."""
    try:
        doc = tomllib.loads(config_text)
    except tomllib.TOMLDecodeError as err:
        raise SurveyError(f"{where}: {err}") from err
    table_in = doc.get("anchors", {})
    if not isinstance(table_in, dict):
        raise SurveyError(f"{where}: anchors: not a table")
    out: dict[str, Any] = {}
    spelt = {anchor_id(k): k for k in table_in}
    positions = result.positions()
    for k, v in table_in.items():
        a = anchor_id(k)
        if a not in positions:
            out[k] = v
            continue
        surveyed = [round(c, 3) for c in positions[a]]
        out[k] = surveyed if not isinstance(v, dict) else {**v, "position_m": surveyed}
    for k, v in out.items():  # an orientation stays, turned with the frame
        if isinstance(v, dict) and isinstance(v.get("orientation_xyzw"), list):
            out[k] = {**v, "orientation_xyzw": turned_xyzw(v["orientation_xyzw"],
                                                           result.frame_turn_deg)}
    for a, p in positions.items():
        if a not in spelt:
            out[str(a)] = [round(c, 3) for c in p]
    doc["anchors"] = out
    text = _comment(header) + write_toml(doc)
    _check(text, where)
    return text


def turned_xyzw(q: Sequence[float], turn_deg: float) -> list[float]:
    """The orientation ``q`` (x, y, z, w) in the frame turned by ``turn_deg`` about z
    (``p' = R(turn) p``): ``q_z(turn) ⊗ q``."""
    half = math.radians(turn_deg) / 2
    s, c = math.sin(half), math.cos(half)
    x, y, z, w = (float(v) for v in q)
    return [round(v, 9) for v in (c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z)]


def _comment(header: str) -> str:
    return "".join(f"# {line}\n" for line in header.splitlines()) + "\n"


def _check(text: str, where: str) -> None:
    try:
        parse(text, where)
    except ConfigError as err:  # a bug here, not the user's: say it as such
        raise RuntimeError(f"the written config would not parse: {err}") from err
