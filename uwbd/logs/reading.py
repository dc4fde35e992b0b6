"""uwbd's MCAP logs read back (:mod:`uwbd.logs.mcaplog` writes them), and recovered.

Reading is a linear scan of the records, so a log cut short by a crash (no footer, which
the seeking reader refuses) reads up to its last complete chunk, and a damaged chunk (a
flipped bit: its CRC fails) costs that chunk only: reading goes on after it
(:func:`intact_records`); ``LogContents.truncated`` says something was lost, ``error`` what
and where. :func:`recover` rewrites such a file, any MCAP file, as a valid one.
"""

from __future__ import annotations

import contextlib
import gc
import io
import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from uwbd import __version__
from uwbd.logs import foxglove as fx
from uwbd.logs.chunked import MCAP0_MAGIC
from uwbd.logs.mcaplog import CHUNK_BYTES, METADATA_NAME
from uwbd.logs.scan import C_SCAN, HEAD, UnusualRecordError, scan


class LogMessage(NamedTuple):
    topic: str
    log_time_ns: int
    data: bytes


@dataclass
class LogContents:
    """Everything in a log, in file order. ``truncated``: the file ended mid-record (a crash);
    what came before its last complete chunk is here."""

    messages: list[LogMessage] = field(default_factory=list)
    metadata: dict[str, str] = field(default_factory=dict)
    truncated: bool = False
    error: str = ""

    def topics(self) -> set[str]:
        return {m.topic for m in self.messages}

    def json(self, topic: str) -> Iterator[dict[str, Any]]:
        return (json.loads(m.data) for m in self.messages if m.topic == topic)


def not_a_log(path: Path) -> str:
    """Why ``path`` cannot be read as an MCAP file ("" when it can): missing, a folder,
    unreadable, empty, or not starting with the MCAP magic."""
    if path.is_dir():
        return f"{path}: is a folder, not an MCAP log"
    try:
        with path.open("rb") as f:
            head = f.read(len(MCAP0_MAGIC))
    except OSError as err:
        return f"cannot read {path}: {err.strerror or err}"
    if not head:
        return f"{path}: the file is empty, not an MCAP log"
    if head != MCAP0_MAGIC:
        return (f"{path}: not an MCAP file (it starts with {head[:4]!r}, an MCAP log with "
                f"{MCAP0_MAGIC[:4]!r})")
    return ""


def read_log(path: Path) -> LogContents:
    """Read a (possibly unfinished) uwbd log by a linear scan. ``/raw/*`` messages come out as
    the bytes read from the port, whether the log wrote them as ``uwbd.Raw`` protobuf
    messages or, before, schemaless (``uwbd.raw``).

    A whole file is read by :func:`uwbd.logs.scan.scan` (one ``struct`` call a message);
    any other (cut short, damaged, compressed otherwise) by the ``mcap`` library's reader,
    which says where it ends."""
    with path.open("rb") as f:
        buf = f.read()
    with _no_cycle_collection():
        try:
            return _read_whole(buf)
        except UnusualRecordError:
            return _read_by_library(path)


@contextlib.contextmanager
def _no_cycle_collection() -> Iterator[None]:
    """The cyclic garbage collector paused: reading makes a record per message and no
    cycle, and a collection every 700 of them walks the growing list again and again
    (measured: a third of reading a 10-minute log)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _read_whole(buf: bytes) -> LogContents:
    out = LogContents()
    topics: dict[int, str] = {}
    raw_protobuf: set[int] = set()
    schemas: dict[int, str] = {}
    messages = out.messages
    append, make = messages.append, tuple.__new__  # make: LogMessage's own __new__, unwrapped
    c_scan = C_SCAN
    for event in scan(buf):
        kind = event[0]
        if kind == "messages":
            if c_scan is not None:  # the loop below, in C
                c_scan.log_messages(event[1], topics, raw_protobuf, fx.decode_raw, LogMessage,
                                    messages)
                continue
            for channel, log_time, record in event[1]:
                data = record
                if channel in raw_protobuf:
                    # uwbd.Raw as uwbd writes it (tag, one-byte length, bytes), else in full
                    if len(data) >= 2 and data[0] == 0x0A and data[1] == len(data) - 2 < 0x80:
                        data = data[2:]
                    else:
                        with contextlib.suppress(ValueError):  # not one: left as it is
                            data = fx.decode_raw(data)
                append(make(LogMessage, (topics.get(channel, "?"), log_time, data)))
        elif kind == "schema":
            schemas[event[1]] = event[2]
        elif kind == "channel":
            _, ident, schema_id, topic, encoding = event
            topics[ident] = topic
            if _raw_protobuf(encoding, schemas.get(schema_id), topic):
                raw_protobuf.add(ident)
        elif event[1] == METADATA_NAME:
            out.metadata = dict(event[2])
    return out


def _raw_protobuf(encoding: str, schema: str | None, topic: str) -> bool:
    """A channel of ``uwbd.Raw`` messages: by its schema, or, where a damaged chunk took the
    schema's record with it (each is written once), by its topic."""
    return encoding == fx.RAW_MESSAGE_ENCODING and (
        schema == fx.RAW_SCHEMA_NAME or (schema is None and topic.startswith("/raw/")))


def _read_by_library(path: Path) -> LogContents:
    out = LogContents()
    channels: dict[int, str] = {}
    raw_protobuf: set[int] = set()  # channels of uwbd.Raw messages (new logs)
    schemas: dict[int, str] = {}
    damage = Damage()
    messages: list[tuple[int, int, bytes]] = []
    for record in intact_records(path.read_bytes(), damage):
        if isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel):
            channels[record.id] = record.topic
            if _raw_protobuf(record.message_encoding, schemas.get(record.schema_id),
                             record.topic):
                raw_protobuf.add(record.id)
        elif isinstance(record, Message):
            messages.append((record.channel_id, record.log_time, record.data))
        elif isinstance(record, Metadata) and record.name == METADATA_NAME:
            out.metadata = dict(record.metadata)
    # topics at the end: a damaged chunk may have held a channel's record, which a finished
    # file's summary section repeats
    for channel, log_time, record_data in messages:
        data = record_data
        if channel in raw_protobuf:
            with contextlib.suppress(ValueError):  # not one: left as it is
                data = fx.decode_raw(record_data)
        out.messages.append(LogMessage(channels.get(channel, "?"), log_time, data))
    if damage:
        out.truncated, out.error = True, damage.said(path)
    return out


@dataclass
class Damage:
    """What :func:`intact_records` had to pass over: damaged stretches (from byte, to byte,
    why), and whether the file ends mid-record (a crash)."""

    skipped: list[tuple[int, int, str]] = field(default_factory=list)
    torn_at: int | None = None  # where the last, unfinished record starts
    torn_why: str = ""

    def __bool__(self) -> bool:
        return bool(self.skipped) or self.torn_at is not None

    def said(self, path: Path) -> str:
        parts = []
        if self.skipped:
            lost = sum(end - start for start, end, _ in self.skipped)
            start, end, why = self.skipped[0]
            parts.append(f"{len(self.skipped)} damaged stretch(es) skipped ({lost} bytes; the "
                         f"first, bytes {start}-{end}: {why}), read on from the next intact "
                         "chunk")
        if self.torn_at is not None:
            parts.append(f"it ends mid-record near byte {self.torn_at} ({self.torn_why})")
        return f"{path}: " + "; ".join(parts)


def intact_records(buf: bytes, damage: Damage) -> Iterator[Any]:
    """Every record of the MCAP file ``buf`` that reads whole and passes its CRC, in file
    order. Where one does not (a flipped bit, a torn write), the next intact chunk is found
    by a scan for a chunk record that reads whole, and reading goes on there: one damaged
    chunk costs that chunk, not the rest of the file. What was passed over goes in
    ``damage``."""
    pos = len(MCAP0_MAGIC)
    while True:
        stream = io.BytesIO(buf)
        stream.seek(pos)
        good_end = pos
        try:
            for record in StreamReader(stream, skip_magic=True, validate_crcs=True).records:
                yield record
                good_end = stream.tell()
            return
        except DAMAGED as err:
            why = f"{type(err).__name__}: {err}"
            resume = _after_record(buf, good_end)
            if resume is None:
                resume = _next_chunk(buf, good_end + 1)
            if resume is None:
                if isinstance(err, (EndOfFile, EOFError, struct.error)):
                    damage.torn_at, damage.torn_why = good_end, why
                else:  # damaged, and nothing intact after it
                    damage.skipped.append((good_end, len(buf), why))
                return
            damage.skipped.append((good_end, resume, why))
            pos = resume


MAX_OPCODE = 0x10


def _after_record(buf: bytes, at: int) -> int | None:
    """Where the record at ``at`` ends by its own length field, if that lands on the start
    of another record that fits the file (a bit flipped in a chunk's contents leaves its
    length intact: skipping just that record loses nothing else); None otherwise."""
    if at + HEAD.size > len(buf):
        return None
    opcode, length = HEAD.unpack_from(buf, at)
    end = int(at + HEAD.size + length)
    if not 0 < opcode <= MAX_OPCODE or end + HEAD.size > len(buf):
        return None
    next_opcode, next_length = HEAD.unpack_from(buf, end)
    if not 0 < next_opcode <= MAX_OPCODE or end + HEAD.size + next_length > len(buf):
        return None
    if next_opcode == 0x06 and not _whole_chunk(buf[end:end + HEAD.size + next_length]):
        return None
    return end


def _whole_chunk(record: bytes) -> bool:
    """``record`` is one chunk record that decompresses, passes its CRC and holds whole
    records (the reader then finds the end of the bytes, as it would a file cut there)."""
    stream = io.BytesIO(record)
    inner = 0
    try:
        for _ in StreamReader(stream, skip_magic=True, validate_crcs=True).records:
            inner += 1
    except (EndOfFile, EOFError, struct.error):
        return inner > 0 and stream.tell() == len(record)
    except DAMAGED:
        return False
    return inner > 0


_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, size, CRC, compression


def _next_chunk(buf: bytes, start: int) -> int | None:
    """The offset of the first chunk record at or after ``start`` that reads whole, with
    its CRC right (None: none)."""
    i = buf.find(b"\x06", start)
    while i != -1:
        if i + _CHUNK_HEAD.size <= len(buf):
            _, length, *_, compression_len = _CHUNK_HEAD.unpack_from(buf, i)
            if (compression_len <= 16 and 32 <= length <= len(buf) - i - 9
                    and _whole_chunk(buf[i:i + 9 + length])):
                return i
        i = buf.find(b"\x06", i + 1)
    return None


# what reading a damaged or torn file raises: mcap's own errors, a record cut off (EOFError,
# struct.error), a damaged compressed chunk (zstandard, lz4: a RuntimeError), a damaged
# length or size field, which has the reader ask for more than an index holds
# (OverflowError) or allocate exabytes for a chunk's records (MemoryError: found by the
# damaged-log property test)
DAMAGED = (McapError, EOFError, ValueError, struct.error, zstandard.ZstdError, RuntimeError,
           OverflowError, MemoryError)


@dataclass(frozen=True)
class Recovered:
    messages: int
    truncated: bool  # the source ended mid-record
    error: str


def recover(source: Path, target: Path) -> Recovered:
    """Copy every complete record of ``source`` (schemas, channels, messages, metadata,
    attachments) into a new, finished MCAP file ``target`` that seeking readers (Foxglove,
    ``mcap`` tools) open. ``source`` may be any MCAP file, typically one a crash cut short."""
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    count = 0
    damage = Damage()
    with target.open("wb") as out:
        from mcap.writer import CompressionType, Writer  # noqa: PLC0415 - not at start-up

        w = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="", library=f"uwbd {__version__} (recover)")
        records = list(intact_records(source.read_bytes(), damage))
        # schemas and channels first, from anywhere in the file: a damaged first chunk may
        # have held them, and a finished file's summary section repeats them
        for record in records:
            if isinstance(record, Schema) and record.id not in schemas:
                schemas[record.id] = w.register_schema(record.name, record.encoding,
                                                       record.data)
        for record in records:
            if isinstance(record, Channel) and record.id not in channels:
                channels[record.id] = w.register_channel(
                    record.topic, record.message_encoding,
                    schemas.get(record.schema_id, 0), dict(record.metadata))
        for record in records:
            if isinstance(record, Message) and record.channel_id in channels:
                w.add_message(channels[record.channel_id], record.log_time, record.data,
                              record.publish_time, record.sequence)
                count += 1
            elif isinstance(record, Metadata):
                w.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                w.add_attachment(record.create_time, record.log_time, record.name,
                                 record.media_type, record.data)
        w.finish()  # type: ignore[no-untyped-call]
    return Recovered(count, bool(damage), damage.said(source) if damage else "")
