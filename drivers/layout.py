"""A small engine that decodes and encodes fixed binary layouts from one table.

A wire format is written once, as a tuple of :class:`Field` rows with the datasheet's field
names; :class:`Layout` derives both directions from it, so parser and encoder cannot drift
apart (the pyubx2 habit). Integers are little-endian. ``div`` turns a raw integer into a
physical value (``value = raw / div``) and back (``raw = round(value * div)``, clamped to the
type's range, which is how a device saturates: +180 deg does not fit an int16 angle).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

# kind -> (struct code, size in bytes, min, max); i24 is handled by hand (no struct code).
_KINDS: dict[str, tuple[str, int, int, int]] = {
    "u8": ("B", 1, 0, 0xFF),
    "i16": ("h", 2, -0x8000, 0x7FFF),
    "u16": ("H", 2, 0, 0xFFFF),
    "i24": ("3s", 3, -0x800000, 0x7FFFFF),
    "i32": ("i", 4, -0x80000000, 0x7FFFFFFF),
    "u32": ("I", 4, 0, 0xFFFFFFFF),
    "u64": ("Q", 8, 0, 0xFFFFFFFFFFFFFFFF),
    "f32": ("f", 4, 0, 0),
    "pad": ("s", 1, 0, 0),
}


@dataclass(frozen=True)
class Field:
    """One table row: ``count`` values of ``kind``; for ``pad``, ``count`` bytes kept raw.

    ``div`` is None for values used as raw integers (ids, counters, times).
    """

    name: str
    kind: str
    count: int = 1
    div: float | None = None


class Layout:
    """Decoder and encoder of one fixed layout, built from its table."""

    def __init__(self, fields: tuple[Field, ...]) -> None:
        self.fields = fields
        codes = ["<"]
        # (name, kind, number of struct items, div, index of the first item, pad length)
        self._plan: list[tuple[str, str, int, float | None, int, int]] = []
        index = 0
        for field in fields:
            code = _KINDS[field.kind][0]
            if field.kind == "pad":
                codes.append(f"{field.count}s")
                self._plan.append((field.name, field.kind, 1, None, index, field.count))
                index += 1
            else:
                codes.append(code * field.count)
                self._plan.append((field.name, field.kind, field.count, field.div, index, 0))
                index += field.count
        self._struct = struct.Struct("".join(codes))
        self.size = self._struct.size
        self.offsets = self._offsets()
        self.decode = self._compile_decoder()  # type: ignore[method-assign]

    def _offsets(self) -> dict[str, int]:
        offsets, offset = {}, 0
        for field in self.fields:
            offsets[field.name] = offset
            offset += field.count * (1 if field.kind == "pad" else _KINDS[field.kind][1])
        return offsets

    def _compile_decoder(self) -> Callable[..., dict[str, Any]]:
        """The decoder as one generated function, e.g. for an accel packet::

            def decode(buf, offset=0):
                r = unpack_from(buf, offset)
                return {"acc_mps2": (r[0] / d0, r[1] / d0, r[2] / d0), "temperature_c": r[3] / d1}

        It computes exactly what :meth:`decode` below does, about three times faster; the
        generic method stays as its readable reference and is tested against it.
        """
        env: dict[str, Any] = {"unpack_from": self._struct.unpack_from, "i24": _from_i24}
        items = []
        for k, (name, kind, count, div, index, _) in enumerate(self._plan):
            env[f"d{k}"] = div
            terms = []
            for i in range(index, index + count):
                term = f"i24(r[{i}])" if kind == "i24" else f"r[{i}]"
                terms.append(f"{term} / d{k}" if div is not None else term)
            value = terms[0] if count == 1 else "(" + ", ".join(terms) + ",)"
            items.append(f"{name!r}: {value}")
        source = ("def decode(buf, offset=0):\n    r = unpack_from(buf, offset)\n"
                  "    return {" + ", ".join(items) + "}\n")
        exec(source, env)
        decode: Callable[..., dict[str, Any]] = env["decode"]
        return decode

    def decode(self, buf: bytes | bytearray | memoryview, offset: int = 0) -> dict[str, Any]:
        """Decode ``self.size`` bytes at ``offset``. Scalars for count 1, tuples otherwise."""
        raw = self._struct.unpack_from(buf, offset)
        out: dict[str, Any] = {}
        for name, kind, count, div, index, _ in self._plan:
            values = raw[index : index + count]
            if kind == "i24":
                values = tuple(_from_i24(v) for v in values)
            if div is not None:
                values = tuple(v / div for v in values)
            out[name] = values[0] if count == 1 else tuple(values)
        return out

    def encode(self, values: Mapping[str, Any]) -> bytearray:
        """Encode a mapping of field name to value; absent fields are zero.

        Raises ``ValueError`` for a value that is not finite: a device cannot send one, so an
        encoder asked to is being misused.
        """
        raw: list[Any] = []
        for name, kind, count, div, _, length in self._plan:
            if kind == "pad":
                raw.append(bytes(values.get(name, b"")).ljust(length, b"\0")[:length])
                continue
            value = values.get(name, 0 if count == 1 else (0,) * count)
            items = (value,) if count == 1 else tuple(value)
            if len(items) != count:
                raise ValueError(f"field {name}: expected {count} values, got {len(items)}")
            for item in items:
                raw.append(_to_raw(name, kind, item, div))
        return bytearray(self._struct.pack(*raw))


def _from_i24(data: bytes) -> int:
    return int.from_bytes(data, "little", signed=True)


def _to_raw(name: str, kind: str, value: float, div: float | None) -> Any:
    if kind == "f32":
        return float(value)
    if not math.isfinite(value):
        raise ValueError(f"field {name}: cannot encode non-finite value {value!r}")
    _, _, lo, hi = _KINDS[kind]
    number = round(value * div) if div is not None else int(value)
    number = min(max(number, lo), hi)
    if kind == "i24":
        return number.to_bytes(3, "little", signed=True)
    return number


def sum8(data: bytes | bytearray | memoryview) -> int:
    """Low byte of the plain sum of ``data``: the checksum of WitMotion and Nooploop frames."""
    return sum(data) & 0xFF
