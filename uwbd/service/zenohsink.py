"""Poses and status over Zenoh (docs/fleet.md, "Subscribing").

Keys under the configured prefix (default ``uwbd/<robot name>``): ``<prefix>/pose`` carries the
same JSON as MCAP ``/pose`` (a ``foxglove.PoseInFrame`` object plus uwbd's fields), encoding
``application/json``; ``<prefix>/status`` is published once a second and answered as a query;
``<prefix>/alive`` is a liveliness token. Peer mode by default; mode and endpoints come from
the ``[zenoh]`` config so a deployment can point at a zenohd router.

``put`` never blocks (congestion control DROP), so a slow network cannot stall fusion. The
queryable runs on a Zenoh thread and only reads the last status bytes, swapped atomically.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import zenoh

from drivers.frames import Frame
from uwbd.codec import strict_json
from uwbd.config.zenoh_session import session_config, zenoh_reason
from uwbd.fusion.types import Pose
from uwbd.logs.mcaplog import pose_json

__all__ = ["ZenohSink", "session_config", "zenoh_reason"]


class ZenohSink:
    def __init__(self, zcfg: dict[str, Any], prefix: str, frame_id: str = "enu") -> None:
        self.prefix = prefix
        self.frame_id = frame_id  # the poses' frame, [robot] nav_frame_id
        self.error = ""
        self.session = zenoh.open(session_config(zcfg))
        json_enc = zenoh.Encoding.APPLICATION_JSON
        self._pose = self.session.declare_publisher(f"{self.prefix}/pose", encoding=json_enc)
        self._status = self.session.declare_publisher(f"{self.prefix}/status", encoding=json_enc)
        self._token = self.session.liveliness().declare_token(f"{self.prefix}/alive")
        self.token_holders: int | None = None  # who holds the token, as the last probe found
        self._probing = False
        self._status_bytes = b"{}"
        self._queryable = self.session.declare_queryable(f"{self.prefix}/status", self._on_query)
        # what else declared on this session (the ROS 2 topics), closed before it
        self.close_first: list[Callable[[], None]] = []

    def probe(self, timeout_s: float) -> None:
        """Ask the network who holds this daemon's liveliness token: this session itself,
        and a router that admitted the token's declaration (one whose access control refuses
        this daemon's keys does not hold it, and drops its puts as well). The count lands in
        :attr:`token_holders` when the query ends (on a Zenoh thread)."""
        if self._probing:
            return
        self._probing = True
        replies = [0]

        def on_reply(reply: zenoh.Reply) -> None:
            replies[0] += reply.ok is not None

        def on_end() -> None:
            self.token_holders = replies[0]
            self._probing = False
        self.session.liveliness().get(f"{self.prefix}/alive", timeout=timeout_s,
                                      handler=zenoh.handlers.Callback(on_reply, on_end))

    def _on_query(self, query: zenoh.Query) -> None:
        with query:  # finalises the query promptly
            query.reply(f"{self.prefix}/status", self._status_bytes,
                        encoding=zenoh.Encoding.APPLICATION_JSON)

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        """Raw bytes stay in the log."""

    def frame(self, frame: Frame) -> None:
        """Frames stay in the log."""

    def pose(self, pose: Pose) -> None:
        self._pose.put(pose_json(pose, self.frame_id))

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        self._status_bytes = strict_json(status)
        self._status.put(self._status_bytes)

    def close(self) -> None:
        for close in self.close_first:
            close()
        for entity in (self._queryable, self._token, self._status, self._pose):
            entity.undeclare()
        self.session.close()  # a session left open hangs the interpreter at exit
