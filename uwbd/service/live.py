"""``--foxglove``: the log's channels served live over the Foxglove WebSocket protocol.

A pipeline sink (:class:`uwbd.service.pipeline.Sink`) on ``foxglove-sdk``'s server (the
``foxglove`` extra, ``pip install 'uwbd[foxglove]'``; the daemon without it needs none of
it): the same topics, schemas and JSON as the MCAP log (:mod:`uwbd.logs.foxglove`):
``/pose``, ``/tf``, ``/anchors``, ``/trajectory``, ``/status``, ``/imu``, ``/uwb``,
``/raw/<source>``, and with the demo ``/truth`` and ``/truth/trajectory``. Foxglove connects
with *Open connection → Foxglove WebSocket* to the URL logged at start. The server binds to
127.0.0.1 unless told otherwise.

Nothing is encoded for a channel no client subscribes to: each record costs one check
(``Channel.has_sinks()``, an atomic read in the SDK) while nobody is connected; only the
trajectory's points are kept (two a second), so a client that connects later sees the last
minute. ``/anchors`` is sent once a second, so a client that subscribes late gets it. The
SDK's server runs on threads of its own and queues at most ``message_backlog_size``
messages per client, dropping the oldest: a slow client never blocks the pipeline.
"""

from __future__ import annotations

from typing import Any

import foxglove
from foxglove import Channel, Context

from drivers.frames import Frame, ImuSample, UwbRanges
from uwbd import journal
from uwbd.codec import frame_to_json, strict_json
from uwbd.config import Config
from uwbd.fusion.types import Pose
from uwbd.logs import foxglove as fx
from uwbd.logs.mcaplog import pose_json

DEFAULT_ENDPOINT = "127.0.0.1:8765"
SCENE_PERIOD_NS = 1_000_000_000
LOG = journal.get("live")


def parse_endpoint(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT``, ``PORT`` or ``[IPv6]:PORT`` → (host, port); the host
    defaults to 127.0.0.1. Raises ``ValueError`` saying what is wrong."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = "", text
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(f"{text!r}: write an IPv6 address in brackets, e.g. [::1]:8765")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"{text!r}: expected HOST:PORT, e.g. {DEFAULT_ENDPOINT}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"{text!r}: port {port} is not 0-65535")
    return host or "127.0.0.1", port


class FoxgloveLive:
    """Serves the pipeline's records to Foxglove clients; :meth:`close` stops the server.

    Raises ``RuntimeError`` (the SDK's ``FoxgloveError``) when it cannot listen."""

    def __init__(self, config: Config, host: str = "127.0.0.1", port: int = 8765,
                 name: str = "") -> None:
        self.view = fx.FoxgloveView.from_config(config)
        self._context = Context()
        self.server = foxglove.start_server(name=name or f"uwbd {config.robot_name}",
                                            host=host, port=port, context=self._context)
        self.port = self.server.port
        self.url = f"ws://{f'[{host}]' if ':' in host else host}:{self.port}"
        self._closed = False

        def channel(topic: str, schema: fx.Schema) -> Channel:
            return Channel(topic, schema=schema, context=self._context)

        self._pose = channel("/pose", fx.POSE_SCHEMA)
        self._tf = channel("/tf", fx.FRAME_TRANSFORM_SCHEMA)
        self._trajectory = channel("/trajectory", fx.POSES_IN_FRAME_SCHEMA)
        self._anchors = channel("/anchors", fx.SCENE_UPDATE_SCHEMA)
        self._status = channel("/status", fx.STATUS_SCHEMA)
        self._frames: dict[type[Any], Channel] = {
            cls: channel(*fx.frame_channel(cls)) for cls in (ImuSample, UwbRanges)}
        self._json: dict[str, Channel] = {}  # /truth and the like, made when first sent
        self._raw: dict[str, Channel] = {s.name: self._raw_channel(s.name)
                                         for s in config.sources}
        self._scene_ns: int | None = None
        LOG.info("Foxglove live view at %s (in Foxglove: Open connection → Foxglove "
                 "WebSocket → this URL)", self.url)

    def _raw_channel(self, source: str) -> Channel:
        schema = foxglove.Schema(name=fx.RAW_SCHEMA_NAME, encoding="protobuf",
                                 data=fx.RAW_DESCRIPTOR)
        return Channel(f"/raw/{source}", schema=schema, message_encoding="protobuf",
                       context=self._context)

    @staticmethod
    def _send(channel: Channel, t_ns: int, message: dict[str, Any]) -> None:
        if channel.has_sinks():
            channel.log(strict_json(message), log_time=t_ns)

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        channel = self._raw.get(source)
        if channel is None:
            channel = self._raw[source] = self._raw_channel(source)
        if channel.has_sinks():
            channel.log(fx.encode_raw(data), log_time=t_ns)

    def frame(self, frame: Frame) -> None:
        if self.view.observe(frame):
            self._send(self._anchors, frame.t_ns, self.view.scene(frame.t_ns))
        channel = self._frames.get(type(frame))
        if channel is None:  # a frame type of a newer driver: its own topic
            topic, schema = fx.frame_channel(type(frame))
            channel = self._frames[type(frame)] = Channel(topic, schema=schema,
                                                          context=self._context)
        if channel.has_sinks():
            channel.log(frame_to_json(frame), log_time=frame.t_ns)

    def pose(self, pose: Pose) -> None:
        t_ns, view = pose.t_ns, self.view
        if self._pose.has_sinks():
            self._pose.log(pose_json(pose, view.nav_frame_id), log_time=t_ns)
        if self._tf.has_sinks():
            self._tf.log(strict_json(view.transform(pose)), log_time=t_ns)
        trajectory = view.trajectory(pose)  # kept whether or not anyone watches
        if trajectory is not None:
            self._send(self._trajectory, t_ns, trajectory)
        if self._scene_ns is None or t_ns - self._scene_ns >= SCENE_PERIOD_NS:
            self._scene_ns = t_ns
            if view.anchors_m:
                self._send(self._anchors, t_ns, view.scene(t_ns))

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        self._send(self._status, t_ns, status)

    def json(self, topic: str, t_ns: int, obj: dict[str, Any], schema_name: str = "") -> None:
        """Any other JSON record (the demo's ``/truth``), with uwbd's schema of that name."""
        channel = self._json.get(topic)
        if channel is None:
            schema = fx.SCHEMAS.get(schema_name) or {"type": "object", "properties": {}}
            channel = self._json[topic] = Channel(topic, schema=schema, context=self._context)
        self._send(channel, t_ns, obj)
        if topic == "/truth":
            trajectory = self.view.truth_trajectory(t_ns, obj)
            if trajectory is not None:
                self.json("/truth/trajectory", t_ns, trajectory, "foxglove.PosesInFrame")

    def close(self) -> None:
        """Stop the server (clients see it close) and its channels; again does nothing."""
        if self._closed:
            return
        self._closed = True
        self.server.stop()
        for channel in (self._pose, self._tf, self._trajectory, self._anchors, self._status,
                        *self._frames.values(), *self._json.values(), *self._raw.values()):
            channel.close()
        LOG.debug("Foxglove live view at %s stopped", self.url)
