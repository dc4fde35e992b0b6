"""``uwbd export --ros2``: a log as a ROS 2 bag (a rosbag2 folder: ``metadata.yaml`` and one
MCAP file, CDR messages), written with the pure-Python ``rosbags`` library (the ``tools``
extra), so no ROS installation is needed to write it. It is laid out as ``ros2 bag`` (MCAP
storage) and Foxglove expect; the tests read it back with rosbags' reader (not with a ROS
installation, which this machine does not have).

- ``/uwbd/pose``, ``geometry_msgs/msg/PoseWithCovarianceStamped``: the fused pose in
  ``nav_frame_id`` with its 6×6 covariance;
- ``/uwbd/odom``, ``nav_msgs/msg/Odometry``: the same pose, ``child_frame_id``
  ``body_frame_id``, the twist the velocity in the body frame;
- ``/uwbd/imu``, ``sensor_msgs/msg/Imu``: every IMU sample in the sensor's own axes, frame
  ``<body_frame_id>_imu``;
- ``/tf``, ``tf2_msgs/msg/TFMessage``: ``nav_frame_id`` → ``body_frame_id`` at each pose;
- ``/tf_static``, ``tf2_msgs/msg/TFMessage``: ``body`` → ``body_imu`` (the mounting) and
  ``body`` → ``body_uwb`` (the lever arm), once, offered transient local (latched);
- ``/uwbd/truth``, ``geometry_msgs/msg/PoseStamped``: the log's ``/truth``, if it has one;
- ``/uwbd/diagnostics``, ``diagnostic_msgs/msg/DiagnosticArray``: each pose's health, one
  status ``uwbd: filter`` (level OK when healthy, WARN when not, STALE while waiting; the
  message the health's summary; values its phase, faults, notes, σ and protection levels).

Conventions. uwbd's body frame (forward-left-up) has its origin at the IMU (the pose is the
IMU's), so ``body → body_imu`` is the ``[imu] mounting`` rotation (sensor → body) with no
translation, and ``body → body_uwb`` the ``lever_arm_m`` translation (IMU → antenna, body
axes). The pose covariance orders x, y, z, then rotation about the navigation frame's x,
y, z, as ROS's fixed-axis convention does, so it is copied as it is. ROS puts an odometry
twist in the child frame: the ENU velocity is rotated into the body frame,
``v_b = R(q)ᵀ v_n``. uwbd's poses carry no velocity covariance and no angular rate, so the
twist's angular part is zero and its covariance is marked unknown (``covariance[0] = -1``);
fuse only its linear part, or use ``/uwbd/pose``. The IMU message has no orientation
(``orientation_covariance[0] = -1``); its rate and acceleration covariances are the
diagonal the filter assumes: the config's noise densities squared times the IMU's rate.

Where the poses come from (:func:`export_ros2`): the log's own ``/pose`` when it has some
and no other config is asked for; else the log is replayed (:func:`uwbd.logs.replay.replay`)
with the config given, or its own. The IMU samples are the log's ``/imu`` frames, or its
raw IMU bytes decoded by the drivers.
"""

from __future__ import annotations

import heapq
import math
import shutil
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.stores import ros2_humble as msgs
from tqdm import tqdm

from drivers.frames import ImuSample
from uwbd.config import Config, parse
from uwbd.fusion.core.rotation import quat_from_matrix, quat_to_matrix
from uwbd.fusion.policy.health import Phase, health_from_dict
from uwbd.fusion.types import Pose
from uwbd.logs.reading import LogContents
from uwbd.logs.replay import replay
from uwbd.tools.logtools import decoded_frames, load_recording

# ROS 2 message classes (Humble's definitions)
Time = msgs.builtin_interfaces__msg__Time
Point = msgs.geometry_msgs__msg__Point
RosPose = msgs.geometry_msgs__msg__Pose
PoseStamped = msgs.geometry_msgs__msg__PoseStamped
PoseWithCovariance = msgs.geometry_msgs__msg__PoseWithCovariance
PoseWithCovarianceStamped = msgs.geometry_msgs__msg__PoseWithCovarianceStamped
Quaternion = msgs.geometry_msgs__msg__Quaternion
Transform = msgs.geometry_msgs__msg__Transform
TransformStamped = msgs.geometry_msgs__msg__TransformStamped
Twist = msgs.geometry_msgs__msg__Twist
TwistWithCovariance = msgs.geometry_msgs__msg__TwistWithCovariance
Vector3 = msgs.geometry_msgs__msg__Vector3
Odometry = msgs.nav_msgs__msg__Odometry
Imu = msgs.sensor_msgs__msg__Imu
Header = msgs.std_msgs__msg__Header
TFMessage = msgs.tf2_msgs__msg__TFMessage
DiagnosticArray = msgs.diagnostic_msgs__msg__DiagnosticArray
DiagnosticStatus = msgs.diagnostic_msgs__msg__DiagnosticStatus
KeyValue = msgs.diagnostic_msgs__msg__KeyValue

# The message definitions of these types are the same from Humble to Kilted (same RIHS01
# hashes); bag format version 8 (Jazzy's) keeps the QoS profiles a string, which Humble's
# rosbag2 reads too.
BAG_VERSION: Literal[8] = 8
TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
POSE_TOPIC = "/uwbd/pose"
ODOM_TOPIC = "/uwbd/odom"
IMU_TOPIC = "/uwbd/imu"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TRUTH_TOPIC = "/uwbd/truth"
DIAGNOSTICS_TOPIC = "/uwbd/diagnostics"
TOPIC_TYPES = {
    DIAGNOSTICS_TOPIC: DiagnosticArray.__msgtype__,
    POSE_TOPIC: PoseWithCovarianceStamped.__msgtype__,
    ODOM_TOPIC: Odometry.__msgtype__,
    IMU_TOPIC: Imu.__msgtype__,
    TF_TOPIC: TFMessage.__msgtype__,
    TF_STATIC_TOPIC: TFMessage.__msgtype__,
    TRUTH_TOPIC: PoseStamped.__msgtype__,
}
IMU_SUFFIX = "_imu"  # the IMU's frame: <body_frame_id>_imu, the sensor's own axes
ANTENNA_SUFFIX = "_uwb"  # the UWB antenna's frame: <body_frame_id>_uwb
_DEFAULT_TIME = QosTime(0, 0)  # unspecified: the middleware's default (infinite)


def _qos(depth: int, durability: QosDurability) -> Qos:
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, durability,
               _DEFAULT_TIME, _DEFAULT_TIME, QosLiveliness.AUTOMATIC, _DEFAULT_TIME, False)


STREAM_QOS = _qos(10, QosDurability.VOLATILE)
# as tf2's static broadcaster offers it: `ros2 bag play` then latches the static transforms
STATIC_QOS = _qos(1, QosDurability.TRANSIENT_LOCAL)


@dataclass(frozen=True)
class FrameIds:
    """The frame names in the bag, from the config's ``[robot]`` section."""

    nav: str = "enu"
    body: str = "base_link"

    @classmethod
    def of(cls, config: Config) -> FrameIds:
        return cls(config.nav_frame_id, config.body_frame_id)

    @property
    def imu(self) -> str:
        return self.body + IMU_SUFFIX

    @property
    def antenna(self) -> str:
        return self.body + ANTENNA_SUFFIX


@dataclass(frozen=True)
class TruthPose:
    t_ns: int
    position_m: tuple[float, float, float]
    orientation_xyzw: tuple[float, float, float, float]


@dataclass
class Exported:
    """What :func:`export_ros2` wrote: the bag folder, messages per topic, and whether the
    poses were the log's own (``"log"``) or replayed (``"replay"``)."""

    path: Path
    counts: dict[str, int] = field(default_factory=dict)
    poses_from: str = "log"


# -- reading the log -------------------------------------------------------------------------


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def _vec3(v: Sequence[Any]) -> tuple[float, float, float]:
    return (_num(v[0]), _num(v[1]), _num(v[2]))


def log_poses(contents: LogContents) -> list[Pose]:
    """The log's ``/pose`` messages as poses (``null``, a number that was not finite, as NaN),
    with their health records."""
    out: list[Pose] = []
    for d in contents.json("/pose"):
        p, q = d["pose"]["position"], d["pose"]["orientation"]
        out.append(Pose(
            t_ns=int(d["t_ns"]), position_m=_vec3([p["x"], p["y"], p["z"]]),
            velocity_mps=_vec3(d.get("velocity_mps") or [None] * 3),
            orientation_xyzw=(_num(q["x"]), _num(q["y"]), _num(q["z"]), _num(q["w"])),
            covariance=tuple(_num(c) for c in d.get("covariance") or [None] * 36),
            status=str(d.get("status", "")), heading_observable=bool(d.get("heading_observable")),
            health=health_from_dict(d.get("health") or {})))
    return out


def log_truth(contents: LogContents) -> list[TruthPose]:
    out: list[TruthPose] = []
    for d in contents.json("/truth"):
        p, q = d["pose"]["position"], d["pose"]["orientation"]
        out.append(TruthPose(int(d["t_ns"]), _vec3([p["x"], p["y"], p["z"]]),
                             (_num(q["x"]), _num(q["y"]), _num(q["z"]), _num(q["w"]))))
    return out


def log_imu(contents: LogContents, where: str, config_toml: str | None = None) -> list[ImuSample]:
    """The log's decoded ``/imu`` frames, or (a log of raw bytes only) its raw channels
    decoded by the drivers its metadata names."""
    if any(m.topic == "/imu" for m in contents.messages):
        return [f for f in decoded_frames(contents, ("/imu",), where)
                if isinstance(f, ImuSample)]
    if not any(m.topic.startswith("/raw/") for m in contents.messages):
        return []
    rec = load_recording(contents, where, config_toml)
    return [f for f in rec.frames if isinstance(f, ImuSample)]


# -- messages --------------------------------------------------------------------------------


def stamp(t_ns: int) -> Time:
    return Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def _header(t_ns: int, frame_id: str) -> Header:
    return Header(stamp=stamp(t_ns), frame_id=frame_id)


def _quat(xyzw: Sequence[float]) -> Quaternion:
    return Quaternion(x=float(xyzw[0]), y=float(xyzw[1]), z=float(xyzw[2]), w=float(xyzw[3]))


def _ros_pose(position: Sequence[float], xyzw: Sequence[float]) -> RosPose:
    return RosPose(position=Point(x=float(position[0]), y=float(position[1]),
                                  z=float(position[2])), orientation=_quat(xyzw))


def _vector(v: Sequence[float]) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose_with_covariance(pose: Pose) -> PoseWithCovariance:
    return PoseWithCovariance(pose=_ros_pose(pose.position_m, pose.orientation_xyzw),
                              covariance=np.array(pose.covariance, dtype=np.float64))


def body_velocity(pose: Pose) -> tuple[float, float, float]:
    """The pose's ENU velocity in the body frame: ``R(q)ᵀ v_n``."""
    x, y, z, w = pose.orientation_xyzw
    v = quat_to_matrix(np.array([w, x, y, z])).T @ np.array(pose.velocity_mps)
    return (float(v[0]), float(v[1]), float(v[2]))


def pose_msg(pose: Pose, frames: FrameIds) -> PoseWithCovarianceStamped:
    return PoseWithCovarianceStamped(header=_header(pose.t_ns, frames.nav),
                                     pose=_pose_with_covariance(pose))


def odometry_msg(pose: Pose, frames: FrameIds) -> Odometry:
    twist_cov = np.zeros(36)
    twist_cov[0] = -1.0  # unknown: uwbd's poses carry no velocity covariance
    return Odometry(
        header=_header(pose.t_ns, frames.nav), child_frame_id=frames.body,
        pose=_pose_with_covariance(pose),
        twist=TwistWithCovariance(twist=Twist(linear=_vector(body_velocity(pose)),
                                              angular=_vector((0.0, 0.0, 0.0))),
                                  covariance=twist_cov))


def tf_msg(pose: Pose, frames: FrameIds) -> TFMessage:
    return TFMessage(transforms=[TransformStamped(
        header=_header(pose.t_ns, frames.nav), child_frame_id=frames.body,
        transform=Transform(translation=_vector(pose.position_m),
                            rotation=_quat(pose.orientation_xyzw)))])


def static_tf_msg(t_ns: int, config: Config, frames: FrameIds) -> TFMessage:
    """``body → body_imu``: the mounting rotation (sensor → body), the IMU at the body's
    origin; ``body → body_uwb``: the lever arm (IMU → antenna, body axes)."""
    w, x, y, z = quat_from_matrix(np.array(config.mounting, dtype=np.float64))
    return TFMessage(transforms=[
        TransformStamped(header=_header(t_ns, frames.body), child_frame_id=frames.imu,
                         transform=Transform(translation=_vector((0.0, 0.0, 0.0)),
                                             rotation=_quat((x, y, z, w)))),
        TransformStamped(header=_header(t_ns, frames.body), child_frame_id=frames.antenna,
                         transform=Transform(translation=_vector(config.lever_arm_m),
                                             rotation=_quat((0.0, 0.0, 0.0, 1.0)))),
    ])


def imu_variances(config: Config, samples: Sequence[ImuSample]) -> tuple[float, float]:
    """(gyro, accel) per-sample variances the filter assumes: noise density² × the IMU's
    rate (the median sample interval's inverse); zeros (unknown) under two samples."""
    if len(samples) < 2:
        return 0.0, 0.0
    dt_ns = float(np.median(np.diff([s.t_ns for s in samples])))
    if dt_ns <= 0:
        return 0.0, 0.0
    rate_hz = 1e9 / dt_ns
    noise = config.filter_config().imu_noise
    return noise.gyro ** 2 * rate_hz, noise.acc ** 2 * rate_hz


def imu_msg(sample: ImuSample, frames: FrameIds, gyro_var: float = 0.0,
            acc_var: float = 0.0) -> Imu:
    orientation_cov = np.zeros(9)
    orientation_cov[0] = -1.0  # no orientation
    return Imu(header=_header(sample.t_ns, frames.imu), orientation=_quat((0.0, 0.0, 0.0, 1.0)),
               orientation_covariance=orientation_cov,
               angular_velocity=_vector(sample.gyro_rps),
               angular_velocity_covariance=np.diag([gyro_var] * 3).ravel(),
               linear_acceleration=_vector(sample.acc_mps2),
               linear_acceleration_covariance=np.diag([acc_var] * 3).ravel())


def diagnostics_msg(pose: Pose, hardware_id: str) -> DiagnosticArray:
    """A pose's health as ROS diagnostics (``diagnostic_msgs``' levels: 0 OK, 1 WARN,
    3 STALE)."""
    h = pose.health
    level = 0 if h.healthy else 3 if h.phase is Phase.WAITING else 1

    def text(x: float | None) -> str:
        return "" if x is None else f"{x:.4f}"
    values = [("phase", h.phase.value), ("faults", ",".join(h.faults)),
              ("notes", ",".join(h.notes)), ("position_sigma_m", text(h.position_sigma_m)),
              ("horizontal_protection_m", text(h.horizontal_protection_m)),
              ("vertical_protection_m", text(h.vertical_protection_m))]
    return DiagnosticArray(header=_header(pose.t_ns, ""), status=[DiagnosticStatus(
        level=level, name="uwbd: filter", message=h.summary(),
        hardware_id=hardware_id, values=[KeyValue(key=k, value=v) for k, v in values])])


def truth_msg(truth: TruthPose, frames: FrameIds) -> PoseStamped:
    return PoseStamped(header=_header(truth.t_ns, frames.nav),
                       pose=_ros_pose(truth.position_m, truth.orientation_xyzw))


# -- writing ---------------------------------------------------------------------------------


def write_bag(out: Path, config: Config, poses: Sequence[Pose], imu: Sequence[ImuSample],
              truth: Sequence[TruthPose] = (), progress: bool = False) -> dict[str, int]:
    """Write the bag folder ``out``, messages in time order; the messages per topic.
    ``/uwbd/truth`` is there when ``truth`` is not empty. ``out`` must not exist (else
    ``rosbags.rosbag2.WriterError``); on an error while writing, the folder is removed."""
    frames = FrameIds.of(config)
    gyro_var, acc_var = imu_variances(config, imu)
    times = [p.t_ns for p in poses] + [s.t_ns for s in imu] + [t.t_ns for t in truth]
    start_ns = min(times) if times else 0

    def stream(topic: str, items: Iterable[tuple[int, object]]) -> Iterator[
            tuple[int, str, object]]:
        return ((t, topic, msg) for t, msg in items)

    streams = [
        stream(TF_STATIC_TOPIC, [(start_ns, static_tf_msg(start_ns, config, frames))]),
        stream(POSE_TOPIC, ((p.t_ns, pose_msg(p, frames)) for p in poses)),
        stream(ODOM_TOPIC, ((p.t_ns, odometry_msg(p, frames)) for p in poses)),
        stream(TF_TOPIC, ((p.t_ns, tf_msg(p, frames)) for p in poses)),
        stream(IMU_TOPIC, ((s.t_ns, imu_msg(s, frames, gyro_var, acc_var)) for s in imu)),
        stream(DIAGNOSTICS_TOPIC, ((p.t_ns, diagnostics_msg(p, config.robot_name))
                                   for p in poses)),
    ]
    topics = [TF_STATIC_TOPIC, POSE_TOPIC, ODOM_TOPIC, TF_TOPIC, IMU_TOPIC, DIAGNOSTICS_TOPIC]
    if truth:
        streams.append(stream(TRUTH_TOPIC, ((t.t_ns, truth_msg(t, frames)) for t in truth)))
        topics.append(TRUTH_TOPIC)
    total = 1 + 4 * len(poses) + len(imu) + len(truth)
    # refuses an existing folder (WriterError), which is then left alone
    writer = Writer(out, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    try:
        writer.open()  # creates the folder
        connections: dict[str, Connection] = {
            topic: writer.add_connection(
                topic, TOPIC_TYPES[topic], typestore=TYPESTORE,
                offered_qos_profiles=[STATIC_QOS if topic == TF_STATIC_TOPIC else STREAM_QOS])
            for topic in topics}
        counts = dict.fromkeys(topics, 0)
        # each stream is in time order; merged by time (ties keep the streams' order)
        merged = heapq.merge(*streams, key=lambda item: item[0])
        for t_ns, topic, msg in tqdm(merged, total=total, desc="export", unit="msg",
                                     disable=not progress, leave=False, mininterval=0.5):
            writer.write(connections[topic], t_ns,
                         TYPESTORE.serialize_cdr(msg, TOPIC_TYPES[topic]))
            counts[topic] += 1
        writer.close()
    except BaseException:
        if writer.storage is not None:
            writer.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    return counts


def export_ros2(contents: LogContents, where: str, out: Path, config_toml: str | None = None,
                progress: bool = False) -> Exported:
    """Write a log as a ROS 2 bag folder ``out``. ``config_toml``: the config to use instead of
    the log's own (what ``-c``/``--set`` make); with it, or when the log has no ``/pose``,
    the poses are those of a replay, else the log's own. Raises ``ConfigError`` for a bad
    config, ``OSError`` when the bag cannot be written (nothing is left behind)."""
    if config_toml is None:
        config = parse(contents.metadata.get("config_toml", ""), f"{where} (metadata)")
    else:
        config = parse(config_toml, f"{where} (with -c/--set)")
    poses = log_poses(contents) if config_toml is None else []
    poses_from = "log"
    if not poses:
        _, kept = replay(contents, where, progress=progress, config_toml=config_toml)
        poses, poses_from = kept.poses, "replay"
    counts = write_bag(out, config, poses, log_imu(contents, where, config_toml),
                       log_truth(contents), progress)
    return Exported(out, counts, poses_from)
