"""A lean linear scan of a whole, well-formed MCAP file: the records ``read_log`` keeps.

The ``mcap`` library's ``StreamReader`` makes about a dozen Python calls per message (its
stream reads one field at a time); a replay of a 10-minute log spent as long reading the
file as fusing it. Here the file is read at once and each record is unpacked with one
``struct`` call: the same schemas, channels, messages and metadata, in the same order.

It handles exactly the files it can vouch for: anything it does not expect — a record
cut short (a crash), a chunk whose CRC does not match, a compression other than zstd or
none, a record whose fields do not fill it, a data-section CRC — raises :class:`UnusualRecordError`,
and :func:`uwbd.logs.reading.read_log` then reads the file with the library's reader,
which says what is wrong and where.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import zstandard

from uwbd.fusion.core import native

MAGIC = b"\x89MCAP0\r\n"
HEAD = struct.Struct("<BQ")  # a record's opcode and length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed CRC
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x03, 0x04, 0x05, 0x06
OP_FOOTER, OP_METADATA, OP_DATA_END = 0x02, 0x0C, 0x0F


def _c_scan() -> ModuleType | None:
    """The per-message loops in C (``_scan.c``), when built and not ruled out by
    ``UWBD_PURE_PYTHON`` (the C core's switch)."""
    if native.core is None:
        return None
    try:
        from uwbd.logs import _scan  # noqa: PLC0415
    except ImportError:
        return None
    return _scan


C_SCAN = _c_scan()


class UnusualRecordError(Exception):
    """The file holds something this scan does not vouch for: read it the library's way."""


# what a scan yields, in file order: ("schema", id, name), ("channel", id, schema id, topic,
# message encoding), ("messages", [(channel id, log time, data), …]), ("metadata", name, {…})
Event = tuple[Any, ...]


def scan(buf: bytes) -> Iterator[Event]:
    """Every record of the MCAP file ``buf`` that ``read_log`` keeps; raises
    :class:`UnusualRecordError` (``struct.error`` is caught and raised as one)."""
    try:
        yield from _scan(buf)
    except struct.error as err:
        raise UnusualRecordError(str(err)) from err


def _scan(buf: bytes) -> Iterator[Event]:
    if buf[:8] != MAGIC:
        raise UnusualRecordError("magic")
    for op, body, stop in _records(buf, 8):
        if op == OP_CHUNK:
            yield from _chunk(buf, body, stop)
        elif op == OP_MESSAGE:
            yield ("messages", _messages(buf, body, stop))
        elif op in (OP_SCHEMA, OP_CHANNEL):
            yield _definition(buf, op, body, stop)
        elif op == OP_METADATA:
            name, k = _string(buf, body)
            pairs, k = _map(buf, k)
            yield ("metadata", name, pairs)
        elif op == OP_DATA_END:
            if _U32.unpack_from(buf, body)[0] != 0:
                raise UnusualRecordError("a data-section CRC")  # the library checks it
        elif op == OP_FOOTER:
            if buf[stop:stop + 8] != MAGIC:
                raise UnusualRecordError("no magic after the footer")
            return
    raise UnusualRecordError("no footer")


def _records(buf: bytes, pos: int) -> Iterator[tuple[int, int, int]]:
    """Each record from ``pos`` to the end of ``buf``: its opcode and where its body starts
    and stops."""
    end = len(buf)
    head = HEAD.unpack_from
    while pos < end:
        if pos + 9 > end:
            raise UnusualRecordError("ends mid-record")
        op, length = head(buf, pos)
        body = pos + 9
        pos = body + length
        if pos > end:
            raise UnusualRecordError("ends mid-record")
        yield op, body, pos


def _chunk(buf: bytes, body: int, stop: int) -> Iterator[Event]:
    _, _, size, crc = _CHUNK.unpack_from(buf, body)
    compression, k = _string(buf, body + _CHUNK.size)
    (n,) = _U64.unpack_from(buf, k)
    k += 8
    if k + n != stop:
        raise UnusualRecordError("chunk length")
    if compression == "zstd":
        try:
            data = zstandard.ZstdDecompressor().decompress(buf[k:stop], max_output_size=size)
        except zstandard.ZstdError as err:
            raise UnusualRecordError("zstd") from err
    elif compression == "":
        data = buf[k:stop]
    else:
        raise UnusualRecordError(f"compression {compression}")
    if len(data) != size or (crc != 0 and zlib.crc32(data) != crc):
        raise UnusualRecordError("chunk CRC")
    messages: list[tuple[int, int, bytes]] = []
    message = _MESSAGE.unpack_from
    head = HEAD.unpack_from
    append = messages.append
    end, nxt = len(data), 0
    while nxt < end:  # _records(data, 0), inline: a chunk holds thousands of messages
        if C_SCAN is not None:  # the run of messages from here in one call (the same)
            try:
                run, nxt = C_SCAN.chunk_messages(data, nxt)
            except ValueError as err:
                raise UnusualRecordError(str(err)) from err
            messages += run
            if nxt >= end:
                break
        if nxt + 9 > end:
            raise UnusualRecordError("ends mid-record")
        op, length = head(data, nxt)
        start = nxt + 9
        nxt = start + length
        if nxt > end:
            raise UnusualRecordError("ends mid-record")
        if op == OP_MESSAGE:
            if length < 22:
                raise UnusualRecordError("message length")
            channel, _, log_time, _ = message(data, start)
            append((channel, log_time, data[start + 22:nxt]))
        elif op in (OP_SCHEMA, OP_CHANNEL):
            if messages:
                yield ("messages", messages)
                messages = []
                append = messages.append
            yield _definition(data, op, start, nxt)
    if messages:
        yield ("messages", messages)


def _messages(buf: bytes, body: int, stop: int) -> list[tuple[int, int, bytes]]:
    """A message outside any chunk."""
    if stop - body < 22:
        raise UnusualRecordError("message length")
    channel, _, log_time, _ = _MESSAGE.unpack_from(buf, body)
    return [(channel, log_time, buf[body + 22:stop])]


def _definition(buf: bytes, op: int, body: int, stop: int) -> Event:
    """A schema or a channel; its fields must fill the record exactly."""
    (ident,) = _U16.unpack_from(buf, body)
    if op == OP_SCHEMA:
        name, k = _string(buf, body + 2)
        _, k = _string(buf, k)  # encoding
        (n,) = _U32.unpack_from(buf, k)
        event: Event = ("schema", ident, name)
        k += 4 + n
    else:
        (schema_id,) = _U16.unpack_from(buf, body + 2)
        topic, k = _string(buf, body + 4)
        encoding, k = _string(buf, k)
        _, k = _map(buf, k)
        event = ("channel", ident, schema_id, topic, encoding)
    if k != stop:
        raise UnusualRecordError("record length")
    return event


def _string(buf: bytes, k: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, k)
    k += 4
    if k + n > len(buf):
        raise UnusualRecordError("string")
    try:
        return buf[k:k + n].decode(), k + n
    except UnicodeDecodeError as err:
        raise UnusualRecordError("string") from err


def _map(buf: bytes, k: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, k)
    k += 4
    stop = k + n
    pairs: dict[str, Any] = {}
    while k < stop:
        key, k = _string(buf, k)
        pairs[key], k = _string(buf, k)
    if k != stop:
        raise UnusualRecordError("map")
    return pairs, k
