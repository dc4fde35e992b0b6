"""uwbd's MCAP logs read back (:mod:`uwbd.logs.mcaplog` writes them), and recovered.

Reading is a linear scan of the records, so a log cut short by a crash (no footer, which
the seeking reader refuses) reads up to its last complete chunk, and damage (a flipped bit,
a zeroed tail) costs what it damaged only (:mod:`uwbd.logs.intact`);
``LogContents.truncated`` says something was lost, ``error`` what and where. :func:`recover`
rewrites such a file, any MCAP file, as a valid one.
"""

from __future__ import annotations

import contextlib
import gc
import json
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from mcap.records import Attachment, Channel, Message, Metadata, Schema

from uwbd import __version__
from uwbd.codec import MAX_T_NS
from uwbd.logs import foxglove as fx
from uwbd.logs.chunked import MCAP0_MAGIC
from uwbd.logs.intact import Damage, intact_records, intact_size
from uwbd.logs.mcaplog import CHUNK_BYTES, METADATA_NAME
from uwbd.logs.scan import C_SCAN, UnusualRecordError, scan


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
        return (_json_object(m.data) for m in self.messages if m.topic == topic)


def _json_object(data: bytes) -> dict[str, Any]:
    """A JSON record as a dict; one that is not (not UTF-8, not JSON, not an object) as an
    empty one, which its reader skips as a record missing its fields."""
    try:
        value = json.loads(data)
    except ValueError:  # (UnicodeDecodeError and JSONDecodeError are ValueErrors)
        return {}
    return value if isinstance(value, dict) else {}


def not_a_log(path: Path) -> str:
    """Why ``path`` cannot be read as an MCAP file ("" when it can): missing, a folder or
    anything but a regular file (a FIFO would block the read), unreadable, empty, or not
    starting with the MCAP magic."""
    if path.is_dir():
        return f"{path}: is a folder, not an MCAP log"
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            return f"{path}: not a regular file (a FIFO or a device), not an MCAP log"
    except OSError as err:
        return f"cannot read {path}: {err.strerror or err}"
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
    damage = Damage()
    with path.open("rb") as f:
        buf = f.read(intact_size(f, damage))
    with _no_cycle_collection():
        contents = None
        if not damage:
            with contextlib.suppress(UnusualRecordError):
                contents = _read_whole(buf)
        if contents is None:
            contents = _read_by_library(path, buf, damage)
    return _in_time(contents, path)


def _in_time(contents: LogContents, path: Path) -> LogContents:
    """Messages whose log time no int64 nanosecond holds (past 2262: a damaged or foreign
    log's) are left out, and said."""
    if contents.messages and max(m.log_time_ns for m in contents.messages) > MAX_T_NS:
        kept = [m for m in contents.messages if m.log_time_ns <= MAX_T_NS]
        said = (f"{path}: {len(contents.messages) - len(kept)} messages with log times past "
                "2^63 - 1 ns (the year 2262) left out")
        contents.messages = kept
        contents.truncated = True
        contents.error = f"{contents.error}; {said}" if contents.error else said
    return contents


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


def _read_by_library(path: Path, buf: bytes, damage: Damage) -> LogContents:
    out = LogContents()
    channels: dict[int, str] = {}
    raw_protobuf: set[int] = set()  # channels of uwbd.Raw messages (new logs)
    schemas: dict[int, str] = {}
    messages: list[tuple[int, int, bytes]] = []
    for record in intact_records(buf, damage):
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
        with source.open("rb") as f:
            buf = f.read(intact_size(f, damage))
        records = list(intact_records(buf, damage))
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
