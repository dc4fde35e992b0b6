"""uwbd's MCAP logs: the layout of docs/architecture.md ("The log"), written and read back.

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

Reading the logs back, and recovering a cut one: :mod:`uwbd.logs.reading`.
"""

from __future__ import annotations

import contextlib
import json
import socket
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer

from drivers.frames import Frame, UwbRanges
from uwbd import __version__
from uwbd.codec import frame_to_json, strict_json
from uwbd.fusion.types import Pose
from uwbd.logs import foxglove as fx
from uwbd.logs.chunked import MCAP0_MAGIC, ChunkedWriter

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


class UnencodableError(ValueError):
    """``records`` records of one call could not be encoded (none of them written)."""

    def __init__(self, records: int, reason: str) -> None:
        super().__init__(reason)
        self.records = records


UNENCODABLE = (TypeError, ValueError, struct.error)  # what a record that cannot be encoded raises


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
        self.header_bytes = self.flushed_bytes  # a cut here holds no message

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

    def _add(self, channel: int, t_ns: int, data: bytes, counted: bool = True) -> None:
        """A message; ``counted``: one of the records the log was given (a cut loses it),
        not the anchors' scene each file repeats for its viewers."""
        if self._scene_version != self.view.anchors_version:
            self._scene_version = self.view.anchors_version
            self._add(self._json_channel("/anchors", "foxglove.SceneUpdate", None), t_ns,
                      strict_json(self.view.scene(t_ns)), counted=False)
        self._sequence = (self._sequence + 1) & 0xFFFFFFFF  # MCAP's sequence is 32 bits
        self.unflushed += counted
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
