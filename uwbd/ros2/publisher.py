"""The daemon's live ROS 2 topics (``[ros2] enabled``): a pipeline sink that publishes, on
the daemon's own Zenoh session, what a ROS 2 node running rmw_zenoh subscribes to, so
``ros2 topic echo /uwbd/pose`` sees the poses with no bridge and no ROS 2 on the robot.

- one node (``[ros2] node_name`` in ``namespace``) and a publisher per topic that is on, each
  with its liveliness token (design.md, "Graph Cache"): ``ros2 node list`` and ``ros2 topic
  list`` see them;
- each sample is the message's CDR on the topic's key (design.md, "Topic and Service name
  mapping"), with the 33-byte attachment ("Publishers"): its publisher's sequence number
  from 1, the wall clock at publishing, the publisher's GID;
- QoS as a ROS 2 node offers it: reliable, volatile, keep last 10; ``/tf_static`` transient
  local, depth 1, as tf2's static broadcaster: rmw_zenoh's advanced publisher with a
  one-sample cache, publisher detection and sporadic heartbeats (``rmw_publisher_data.cpp``),
  so a late subscriber still gets the transforms;
- the pose, odometry and transform at every pose; each IMU sample right after the pose its
  read brings out (so the pose is not kept waiting, and a read's messages leave together),
  within 50 ms; the diagnostics with every status (once a second); the static transforms
  once at start.

Puts never block (congestion control DROP, as rmw_zenoh's volatile publishers): a slow
subscriber cannot stall fusion. The messages are :mod:`uwbd.ros2.messages`, the names
:mod:`uwbd.ros2.rmw_zenoh`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from drivers.frames import Frame, ImuSample
from uwbd.config import Config
from uwbd.config.ros2 import NO_TYPE_HASH
from uwbd.fusion.types import Pose, health_from_dict
from uwbd.ros2 import rmw_zenoh as rz
from uwbd.ros2.cdr import imu_layout, pose_layouts
from uwbd.ros2.messages import (
    TYPES,
    TYPESTORE,
    FrameIds,
    diagnostics_msg,
    imu_values,
    imu_variances,
    static_tf_msg,
)

NODE_ID = 0  # the node's id in its context; its publishers' ids follow from 1
STREAM_QOS = rz.Qos(depth=10)
STATIC_QOS = rz.Qos(durability=rz.TRANSIENT_LOCAL, depth=1)
HEARTBEAT_S = 0.5  # rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (ms → s)
RATE_SAMPLES = 64  # IMU samples timed before their covariances are filled in
# IMU samples wait for the pose they bring out at most this long (poses come at 50 Hz)
IMU_HOLD_MAX_NS = 50_000_000


class Topic:
    """One ROS 2 publisher: its key, liveliness token, GID and sequence numbers."""

    def __init__(self, session: zenoh.Session, key: str, token: str, qos: rz.Qos,
                 msgtype: str, clock_ns: Callable[[], int]) -> None:
        self.key, self.token, self.msgtype = key, token, msgtype
        self.gid = rz.gid(token)
        self.sent = 0  # the last sequence number used
        self._clock_ns = clock_ns
        self.publisher: Any
        if qos.durability == rz.TRANSIENT_LOCAL:
            self.publisher = zenoh.ext.declare_advanced_publisher(
                session, key, cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=HEARTBEAT_S),
                reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.DROP)
        else:
            self.publisher = session.declare_publisher(
                key, reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.DROP)
        # as rmw_zenoh: the publisher first, then the token that announces it
        self.liveliness: Any = session.liveliness().declare_token(token)

    def put(self, payload: bytes) -> None:
        self.sent += 1
        self.publisher.put(payload, attachment=rz.attachment(self.sent, self._clock_ns(),
                                                             self.gid))

    def put_message(self, msg: object) -> None:
        self.put(bytes(TYPESTORE.serialize_cdr(msg, self.msgtype)))

    def close(self) -> None:
        self.liveliness.undeclare()
        self.publisher.undeclare()


class Ros2Sink:
    """The pipeline sink of the ROS 2 topics, on a Zenoh session it does not own (closed
    before it)."""

    def __init__(self, session: zenoh.Session, config: Config,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        s = config.ros2_settings
        self.settings = s
        self.config = config
        self.frames = FrameIds.of(config)
        self.hardware_id = config.robot_name
        self.error = ""
        self._imu_held: list[tuple[int, tuple[float, ...]]] = []  # (t_ns, numbers)
        zid = str(session.info.zid())
        self.node_token = rz.node_token(s.domain_id, zid, NODE_ID, s.namespace, s.node_name)
        self._node: Any = session.liveliness().declare_token(self.node_token)
        self.topics: dict[str, Topic] = {}
        try:
            for entity_id, (role, name) in enumerate(s.published.items(), start=1):
                msgtype = TYPES[role]
                dds_type = rz.dds_type_name(msgtype)
                hash_ = (rz.NO_TYPE_HASH if s.distro in NO_TYPE_HASH
                         else TYPESTORE.hash_rihs01(msgtype))
                qos = STATIC_QOS if role == "tf_static" else STREAM_QOS
                self.topics[role] = Topic(
                    session, rz.topic_key(s.domain_id, name, dds_type, hash_),
                    rz.publisher_token(s.domain_id, zid, NODE_ID, entity_id, s.namespace,
                                       s.node_name, name, dds_type, hash_, qos),
                    qos, msgtype, clock_ns)
        except BaseException:
            self.close()
            raise
        self._imu_times: list[int] = []
        self._imu_var = (0.0, 0.0)  # unknown until the IMU's rate is
        self._imu = imu_layout(self.frames)
        layouts = pose_layouts(self.frames)
        self._pose_topics = [(self.topics[role], layouts[role]) for role in layouts
                             if role in self.topics]
        if "tf_static" in self.topics:
            self.topics["tf_static"].put_message(static_tf_msg(clock_ns(), config, self.frames))

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        """Raw bytes stay in the log."""

    def frame(self, frame: Frame) -> None:
        if type(frame) is not ImuSample or "imu" not in self.topics:
            return
        if len(self._imu_times) < RATE_SAMPLES:
            self._imu_times.append(frame.t_ns)
            if len(self._imu_times) == RATE_SAMPLES:
                self._imu_var = imu_variances(self.config, self._imu_times)
        # held until the pose these samples bring (the uwbd/…/pose JSON and the ROS 2 pose
        # leave first, and all of a read's samples in one burst), or until they would be
        # late: no pose (the filter waiting), or the IMU read alone
        if self._imu_held and frame.t_ns - self._imu_held[0][0] > IMU_HOLD_MAX_NS:
            self._flush_imu()
        self._imu_held.append((frame.t_ns, imu_values(frame, *self._imu_var)))

    def _flush_imu(self) -> None:
        held, self._imu_held = self._imu_held, []
        topic, layout = self.topics["imu"], self._imu
        for t_ns, values in held:
            topic.put(layout.pack(t_ns, values))

    def pose(self, pose: Pose) -> None:
        for topic, (layout, values) in self._pose_topics:
            topic.put(layout.pack(pose.t_ns, values(pose)))
        if self._imu_held:
            self._flush_imu()

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        """The diagnostics: the filter's health now (which the status holds)."""
        if self._imu_held:
            self._flush_imu()
        if "diagnostics" in self.topics:
            health = health_from_dict(status.get("health") or {})
            self.topics["diagnostics"].put_message(
                diagnostics_msg(t_ns, health, self.hardware_id))

    def counts(self) -> dict[str, int]:
        """Samples published, by fully qualified topic name."""
        names = self.settings.published
        return {names[role]: topic.sent for role, topic in self.topics.items()}

    def close(self) -> None:
        if self._imu_held and "imu" in self.topics:
            with contextlib.suppress(zenoh.ZError):  # what is held, unless the session is gone
                self._flush_imu()
        topics, self.topics = self.topics, {}
        for topic in topics.values():
            topic.close()
        node, self._node = self._node, None
        if node is not None:
            node.undeclare()
