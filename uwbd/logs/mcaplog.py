"""uwbd's MCAP logs: the layout of ARCHITECTURE.md, written and read back.

* ``/raw/<source>``: ``protobuf``, schema ``uwbd.Raw`` (older logs: schemaless, encoding
  ``uwbd.raw``): bytes exactly as read, one message per read;
* ``/imu``, ``/uwb``: ``json``, ``uwbd.ImuSample``, ``uwbd.UwbRanges``: decoded frames
  (:mod:`uwbd.codec`);
* ``/pose``, ``/truth``: ``json``, ``foxglove.PoseInFrame``: the fused pose (plus uwbd's
  fields); ground truth;
* ``/status``: ``json``, ``uwbd.Status``: health and counters;
* ``/tf``, ``/anchors``, ``/trajectory``, ``/truth/trajectory``: ``json``, ``foxglove.*``:
  for viewers (:mod:`uwbd.logs.foxglove`).

Every JSON channel has a JSON Schema (:mod:`uwbd.logs.foxglove`) and every record a
``timestamp {sec, nsec}``.

``log_time`` is the receive time in ns since the Unix epoch. Metadata record ``uwbd``: the uwbd
version, the config TOML as used, the sources (name, driver, port) as JSON, the robot's name
(``[robot] name``) and the host that wrote the file.

Reading is a linear scan of the records, so a log cut short by a crash (no footer, which
the seeking reader refuses) reads up to its last complete chunk; ``LogContents.truncated``
says so. :func:`recover` rewrites such a file, any MCAP file, as a valid one.
"""

from __future__ import annotations

import contextlib
import gc
import json
import socket
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from drivers.frames import Frame, UwbRanges
from uwbd import __version__
from uwbd.codec import frame_to_json, strict_json
from uwbd.fusion.types import Pose
from uwbd.logs import foxglove as fx
from uwbd.logs.chunked import MCAP0_MAGIC, ChunkedWriter
from uwbd.logs.scan import C_SCAN, UnusualRecordError, scan

RAW_ENCODING = fx.LEGACY_RAW_ENCODING  # the old schemaless /raw/* encoding, still read
METADATA_NAME = "uwbd"
CHUNK_BYTES = 64 * 1024  # ~1 s of a 200 Hz IMU + UWB: a crash loses about that much
POSE_SCHEMA = fx.POSE_SCHEMA
NAV_FRAME_ID = "enu"  # the default [robot] nav_frame_id


def pose_message(t_ns: int, position_m: Sequence[float], orientation_xyzw: Sequence[float],
                 extra: dict[str, Any] | None = None,
                 frame_id: str = NAV_FRAME_ID) -> dict[str, Any]:
    """A ``foxglove.PoseInFrame`` JSON object (plus uwbd's own fields, which Foxglove ignores)."""
    x, y, z = map(float, position_m)
    qx, qy, qz, qw = map(float, orientation_xyzw)
    msg: dict[str, Any] = {
        "timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
        "frame_id": frame_id,
        "pose": {"position": {"x": x, "y": y, "z": z},
                 "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}},
        "t_ns": t_ns,
    }
    msg.update(extra or {})
    return msg


def pose_to_message(pose: Pose, frame_id: str = NAV_FRAME_ID) -> dict[str, Any]:
    """``/pose`` (and Zenoh ``<prefix>/pose``): :func:`pose_message` plus velocity,
    covariance, status and the health record, whose unknown values are left out."""
    return pose_message(pose.t_ns, pose.position_m, pose.orientation_xyzw, {
        "velocity_mps": pose.velocity_mps, "covariance": pose.covariance,  # tuples: arrays
        "status": pose.status, "heading_observable": pose.heading_observable,
        "health": known(pose.health.as_dict())}, frame_id)


class _Encoded:
    """The last pose encoded (a one-entry memo for :func:`pose_json`)."""

    pose: Pose | None = None
    frame_id = ""
    data = b""


def pose_json(pose: Pose, frame_id: str = NAV_FRAME_ID) -> bytes:
    """:func:`pose_to_message` as JSON bytes, encoded once for all sinks: the sinks the
    pipeline hands one pose to in turn (log, Zenoh, live viewer) share the bytes of the
    first one's call (a pose is immutable; the last one is kept, with its frame)."""
    last = _Encoded
    if pose is last.pose and frame_id == last.frame_id:
        return last.data
    data = strict_json(pose_to_message(pose, frame_id))
    last.pose, last.frame_id, last.data = pose, frame_id, data
    return data


def known(record: dict[str, Any]) -> dict[str, Any]:
    """``record`` without its ``None`` values: a value not known is left out, not ``null``
    (Foxglove's schemas have no nullable fields)."""
    return {k: v for k, v in record.items() if v is not None}


@dataclass(frozen=True)
class SourceInfo:
    name: str
    driver: str
    port: str = ""


class LogWriter:
    """Writes one MCAP file; use as a context manager so it is finished on every path.

    Beside the records it is given it writes the viewer channels of
    :mod:`uwbd.logs.foxglove` from ``view`` (by default one made from ``config_toml``;
    :class:`uwbd.logs.sink.McapSink` passes the one its files share): ``/tf`` and
    ``/trajectory`` with the poses, ``/truth/trajectory`` with ``/truth``, and ``/anchors``
    with the file's first record and whenever the anchor set changes."""

    def __init__(self, path: Path, config_toml: str = "", sources: tuple[SourceInfo, ...] = (),
                 chunk_bytes: int = CHUNK_BYTES, robot: str = "",
                 view: fx.FoxgloveView | None = None, exclusive: bool = False) -> None:
        """``exclusive``: never replace a file (``FileExistsError`` if ``path`` exists)."""
        self.path = path
        self.view = view if view is not None else fx.FoxgloveView.from_toml(config_toml)
        self._file: IO[bytes] = path.open("xb" if exclusive else "wb")
        self._w = ChunkedWriter(self._file, chunk_bytes)
        self._w.start(library=f"uwbd {__version__}")
        self._w.add_metadata(METADATA_NAME, {
            "version": __version__, "config_toml": config_toml,
            "sources": json.dumps([vars(s) for s in sources]), "robot": robot,
            "host": socket.gethostname()})
        self._channels: dict[str, int] = {}
        self._by_source: dict[str, int] = {}  # /raw/<source>'s channel
        self._by_frame_type: dict[type, int] = {}
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._sequence = 0
        self._scene_version = 0  # the anchors last written to this file
        self.flushed_bytes = 0  # the file is whole records up to here (see finish_cut)
        self.unflushed = 0  # records since then: what a cut there loses
        self.flush()  # header and metadata reach the disk now: a cut file keeps them

    def _channel(self, topic: str, encoding: str, schema_name: str = "",
                 schema: dict[str, Any] | None = None, schema_encoding: str = "jsonschema",
                 schema_data: bytes = b"") -> int:
        if topic not in self._channels:
            schema_id = 0
            if schema is not None:
                schema_data = json.dumps(schema).encode()
            if schema_data:
                key = (schema_name, schema_encoding, schema_data)
                if key not in self._schemas:
                    self._schemas[key] = self._w.register_schema(schema_name, schema_encoding,
                                                                 schema_data)
                schema_id = self._schemas[key]
            self._channels[topic] = self._w.register_channel(topic, encoding, schema_id)
        return self._channels[topic]

    def _add(self, channel: int, t_ns: int, data: bytes) -> None:
        if self._scene_version != self.view.anchors_version:
            self._scene_version = self.view.anchors_version
            self.json("/anchors", t_ns, self.view.scene(t_ns), "foxglove.SceneUpdate")
        self._sequence = (self._sequence + 1) & 0xFFFFFFFF  # MCAP's sequence is 32 bits
        self.unflushed += 1
        self._w.add_message(channel, t_ns, data, self._sequence)

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        channel = self._by_source.get(source)
        if channel is None:
            channel = self._by_source[source] = self._channel(
                f"/raw/{source}", fx.RAW_MESSAGE_ENCODING, fx.RAW_SCHEMA_NAME,
                schema_encoding="protobuf", schema_data=fx.RAW_DESCRIPTOR)
        self._add(channel, t_ns, fx.encode_raw(data))

    def frame(self, frame: Frame) -> None:
        kind = type(frame)
        channel = self._by_frame_type.get(kind)
        if channel is None:
            topic, schema = fx.frame_channel(kind)
            channel = self._by_frame_type[kind] = self._channel(topic, "json", schema["title"],
                                                                schema)
        if kind is UwbRanges:
            self.view.observe(frame)
        self._add(channel, frame.t_ns, frame_to_json(frame))

    def pose(self, pose: Pose, data: bytes | None = None) -> None:
        """``/pose`` (``data``: its bytes, when :func:`pose_json` made them already), and
        the viewer channels that follow it."""
        view = self.view
        self._add(self._json_channel("/pose", "foxglove.PoseInFrame", POSE_SCHEMA), pose.t_ns,
                  pose_json(pose, view.nav_frame_id) if data is None else data)
        self.json("/tf", pose.t_ns, view.transform(pose), "foxglove.FrameTransform")
        trajectory = view.trajectory(pose)
        if trajectory is not None:
            self.json("/trajectory", pose.t_ns, trajectory, "foxglove.PosesInFrame")

    def json(self, topic: str, t_ns: int, obj: dict[str, Any], schema_name: str = "",
             schema: dict[str, Any] | None = None) -> None:
        """A JSON record; ``schema`` defaults to uwbd's schema named ``schema_name``
        (:data:`uwbd.logs.foxglove.SCHEMAS`), and ``/truth`` brings ``/truth/trajectory``."""
        self._add(self._json_channel(topic, schema_name, schema), t_ns, strict_json(obj))
        if topic == "/truth":
            trajectory = self.view.truth_trajectory(t_ns, obj)
            if trajectory is not None:
                self.json("/truth/trajectory", t_ns, trajectory, "foxglove.PosesInFrame")

    def _json_channel(self, topic: str, schema_name: str,
                      schema: dict[str, Any] | None) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channel(topic, "json", schema_name,
                                    schema if schema is not None else fx.SCHEMAS.get(schema_name))
        return channel

    def flush(self) -> None:
        """Close the open chunk and hand it to the OS (about once a second)."""
        self._w.flush()
        self.flushed_bytes = self._file.tell()
        self.unflushed = 0

    def abandon(self) -> None:
        """Close the file as it is, after a write failed (the disk is full): nothing more is
        written to it; :func:`finish_cut` makes it a finished file later."""
        with contextlib.suppress(OSError):  # the buffer cannot be written: it is lost
            self._file.close()

    def close(self) -> None:
        if not self._file.closed:
            self._w.finish()
            self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


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
            if (encoding == fx.RAW_MESSAGE_ENCODING
                    and schemas.get(schema_id) == fx.RAW_SCHEMA_NAME):
                raw_protobuf.add(ident)
        elif event[1] == METADATA_NAME:
            out.metadata = dict(event[2])
    return out


def _read_by_library(path: Path) -> LogContents:
    out = LogContents()
    channels: dict[int, str] = {}
    raw_protobuf: set[int] = set()  # channels of uwbd.Raw messages (new logs)
    schemas: dict[int, str] = {}
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                    if (record.message_encoding == fx.RAW_MESSAGE_ENCODING
                            and schemas.get(record.schema_id) == fx.RAW_SCHEMA_NAME):
                        raw_protobuf.add(record.id)
                elif isinstance(record, Message):
                    data = record.data
                    if record.channel_id in raw_protobuf:
                        with contextlib.suppress(ValueError):  # not one: left as it is
                            data = fx.decode_raw(data)
                    out.messages.append(LogMessage(channels.get(record.channel_id, "?"),
                                                   record.log_time, data))
                elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                    out.metadata = dict(record.metadata)
        except DAMAGED as err:
            # a torn last record (mcap raises struct.error when the stream ends inside one),
            # or a damaged chunk: what came before it is kept
            out.truncated = True
            out.error = f"{path}: {_damage(err, f)}"
    return out


# what reading a damaged or torn file raises: mcap's own errors, a record cut off (EOFError,
# struct.error), a damaged compressed chunk (zstandard, lz4: a RuntimeError), a damaged
# length or size field, which has the reader ask for more than an index holds
# (OverflowError) or allocate exabytes for a chunk's records (MemoryError: found by the
# damaged-log property test)
DAMAGED = (McapError, EOFError, ValueError, struct.error, zstandard.ZstdError, RuntimeError,
           OverflowError, MemoryError)


def _damage(err: BaseException, f: IO[bytes]) -> str:
    kind = ("ends mid-record" if isinstance(err, (EOFError, struct.error, EndOfFile))
            else "is damaged")
    return f"it {kind} near byte {f.tell()} ({type(err).__name__}: {err})"


def finish_cut(path: Path, size: int) -> None:
    """Finish a log whose writing stopped (disk full): keep its first ``size`` bytes, whole
    records up to a chunk's end as :attr:`LogWriter.flushed_bytes` says, and end it with
    the records a finished MCAP file ends with (data end, an empty summary, the footer), so
    every reader opens it. Needs a few dozen bytes of room; raises ``OSError`` without."""
    end = RecordBuilder()
    DataEnd(0).write(end)  # CRC 0: not computed
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(end)
    with path.open("r+b") as f:
        f.truncate(max(size, len(MCAP0_MAGIC)))
        f.seek(0, 2)
        f.write(end.end() + MCAP0_MAGIC)  # type: ignore[no-untyped-call]


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
    count, error = 0, ""
    with source.open("rb") as f, target.open("wb") as out:
        from mcap.writer import CompressionType, Writer  # noqa: PLC0415 - not at start-up

        w = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="", library=f"uwbd {__version__} (recover)")
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Schema):
                    schemas[record.id] = w.register_schema(record.name, record.encoding,
                                                           record.data)
                elif isinstance(record, Channel):
                    channels[record.id] = w.register_channel(
                        record.topic, record.message_encoding,
                        schemas.get(record.schema_id, 0), dict(record.metadata))
                elif isinstance(record, Message) and record.channel_id in channels:
                    w.add_message(channels[record.channel_id], record.log_time, record.data,
                                  record.publish_time, record.sequence)
                    count += 1
                elif isinstance(record, Metadata):
                    w.add_metadata(record.name, dict(record.metadata))
                elif isinstance(record, Attachment):
                    w.add_attachment(record.create_time, record.log_time, record.name,
                                     record.media_type, record.data)
        except DAMAGED as err:
            error = f"{source}: {_damage(err, f)}"
        w.finish()  # type: ignore[no-untyped-call]
    return Recovered(count, bool(error), error)
