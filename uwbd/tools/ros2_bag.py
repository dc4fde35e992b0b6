"""``uwbd export --ros2``: a log as a ROS 2 bag (a rosbag2 folder: ``metadata.yaml`` and one
MCAP file, CDR messages), written with the pure-Python ``rosbags`` library (the ``tools``
extra), so no ROS installation is needed to write it. It is laid out as ``ros2 bag`` (MCAP
storage) and Foxglove expect; the tests read it back with rosbags' reader (not with a ROS
installation, which this machine does not have).

The topics are the daemon's live ones (the config's ``[ros2]`` names, :mod:`uwbd.config.ros2`;
by default ``/uwbd/pose``, ``/uwbd/odom``, ``/uwbd/imu``, ``/tf``, ``/tf_static``,
``/diagnostics``) with the messages of :mod:`uwbd.ros2.messages`, one diagnostics message per
pose, and ``/uwbd/truth`` (``geometry_msgs/msg/PoseStamped``) when the log has truth.
``/tf_static`` is offered transient local (latched), as tf2's static broadcaster does.

Where the poses come from (:func:`export_ros2`): the log's own ``/pose`` when it has some
and no other config is asked for; else the log is replayed (:func:`uwbd.service.replay.replay`)
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
from tqdm import tqdm

from drivers.frames import ImuSample
from uwbd import journal
from uwbd.codec import t_ns_of
from uwbd.config import Config, parse
from uwbd.fusion.types import Pose, health_from_dict
from uwbd.logs.reading import LogContents
from uwbd.ros2.messages import (
    TYPES,
    TYPESTORE,
    FrameIds,
    TruthPose,
    diagnostics_msg,
    imu_msg,
    imu_variances,
    odometry_msg,
    pose_msg,
    static_tf_msg,
    tf_msg,
    truth_msg,
)
from uwbd.service.replay import replay
from uwbd.tools.logtools import decoded_frames, load_recording, truth_poses

# bag format version 8 (Jazzy's) keeps the QoS profiles a string, which Humble's rosbag2
# reads too
BAG_VERSION: Literal[8] = 8
LOG = journal.get("export")
TRUTH_TOPIC = "/uwbd/truth"
_DEFAULT_TIME = QosTime(0, 0)  # unspecified: the middleware's default (infinite)


def _qos(depth: int, durability: QosDurability) -> Qos:
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, durability,
               _DEFAULT_TIME, _DEFAULT_TIME, QosLiveliness.AUTOMATIC, _DEFAULT_TIME, False)


STREAM_QOS = _qos(10, QosDurability.VOLATILE)
# as tf2's static broadcaster offers it: `ros2 bag play` then latches the static transforms
STATIC_QOS = _qos(1, QosDurability.TRANSIENT_LOCAL)

@dataclass
class Exported:
    """What :func:`export_ros2` wrote: the bag folder, messages per topic, and whether the
    poses were the log's own (``"log"``) or replayed (``"replay"``)."""

    path: Path
    counts: dict[str, int] = field(default_factory=dict)  # by topic name
    poses_from: str = "log"
    topics: dict[str, str] = field(default_factory=dict)  # role -> topic name


# -- reading the log -------------------------------------------------------------------------


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def _vec3(v: Sequence[Any]) -> tuple[float, float, float]:
    return (_num(v[0]), _num(v[1]), _num(v[2]))


def log_poses(contents: LogContents, where: str) -> list[Pose]:
    """The log's ``/pose`` messages as poses (``null``, a number that was not finite, as NaN),
    with their health records; a record that is not one is skipped, and said once."""
    out: list[Pose] = []
    bad, first = 0, ""
    for d in contents.json("/pose"):
        try:
            p, q = d["pose"]["position"], d["pose"]["orientation"]
            out.append(Pose(
                t_ns=t_ns_of(d["t_ns"]), position_m=_vec3([p["x"], p["y"], p["z"]]),
                velocity_mps=_vec3(d.get("velocity_mps") or [None] * 3),
                orientation_xyzw=(_num(q["x"]), _num(q["y"]), _num(q["z"]), _num(q["w"])),
                covariance=tuple(_num(c) for c in d.get("covariance") or [None] * 36),
                status=str(d.get("status", "")),
                heading_observable=bool(d.get("heading_observable")),
                health=health_from_dict(d.get("health") or {})))
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            bad += 1
            first = first or f"{type(err).__name__}: {err}"
    if bad:
        LOG.warning("%s: %d of %d /pose records are not poses and were skipped (the first: "
                    "%s)", where, bad, bad + len(out), first)
    return out


def log_truth(contents: LogContents, where: str) -> list[TruthPose]:
    """The log's ``/truth`` poses, as :func:`uwbd.tools.logtools.truth_poses` reads them."""
    t, p, q = truth_poses(contents, where)
    return [TruthPose(int(t_ns), (float(x), float(y), float(z)),
                      (float(qx), float(qy), float(qz), float(qw)))
            for t_ns, (x, y, z), (qw, qx, qy, qz) in zip(t, p, q, strict=True)]


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


# -- writing ---------------------------------------------------------------------------------


def write_bag(out: Path, config: Config, poses: Sequence[Pose], imu: Sequence[ImuSample],
              truth: Sequence[TruthPose] = (), progress: bool = False) -> dict[str, int]:
    """Write the bag folder ``out``, messages in time order; the messages per topic. The
    topics are the config's ``[ros2]`` names (one left empty is left out), and
    ``/uwbd/truth`` when ``truth`` is not empty. ``out`` must not exist (else
    ``rosbags.rosbag2.WriterError``); on an error while writing, the folder is removed."""
    frames = FrameIds.of(config)
    gyro_var, acc_var = imu_variances(config, [s.t_ns for s in imu])
    times = [p.t_ns for p in poses] + [s.t_ns for s in imu] + [t.t_ns for t in truth]
    start_ns = min(times) if times else 0
    made: dict[str, Iterable[tuple[int, object]]] = {
        "tf_static": [(start_ns, static_tf_msg(start_ns, config, frames))],
        "pose": ((p.t_ns, pose_msg(p, frames)) for p in poses),
        "odom": ((p.t_ns, odometry_msg(p, frames)) for p in poses),
        "tf": ((p.t_ns, tf_msg(p, frames)) for p in poses),
        "imu": ((s.t_ns, imu_msg(s, frames, gyro_var, acc_var)) for s in imu),
        "diagnostics": ((p.t_ns, diagnostics_msg(p.t_ns, p.health, config.robot_name))
                        for p in poses),
    }
    named = config.ros2_settings.recorded  # role -> topic
    if truth:
        made["truth"] = ((t.t_ns, truth_msg(t, frames)) for t in truth)
        named["truth"] = TRUTH_TOPIC
    sizes = {"tf_static": 1, "pose": len(poses), "odom": len(poses), "tf": len(poses),
             "imu": len(imu), "diagnostics": len(poses), "truth": len(truth)}
    roles = [role for role in made if role in named]

    def stream(role: str) -> Iterator[tuple[int, str, object]]:
        return ((t, role, msg) for t, msg in made[role])

    # refuses an existing folder (WriterError), which is then left alone
    writer = Writer(out, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    try:
        writer.open()  # creates the folder
        connections: dict[str, Connection] = {
            role: writer.add_connection(
                named[role], TYPES[role], typestore=TYPESTORE,
                offered_qos_profiles=[STATIC_QOS if role == "tf_static" else STREAM_QOS])
            for role in roles}
        counts = dict.fromkeys((named[role] for role in roles), 0)
        # each stream is in time order; merged by time (ties keep the streams' order)
        merged = heapq.merge(*(stream(role) for role in roles), key=lambda item: item[0])
        for t_ns, role, msg in tqdm(merged, total=sum(sizes[r] for r in roles), desc="export",
                                    unit="msg", disable=not progress, leave=False,
                                    mininterval=0.5):
            writer.write(connections[role], t_ns, TYPESTORE.serialize_cdr(msg, TYPES[role]))
            counts[named[role]] += 1
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
    poses = log_poses(contents, where) if config_toml is None else []
    poses_from = "log"
    if not poses:
        _, kept = replay(contents, where, progress=progress, config_toml=config_toml)
        poses, poses_from = kept.poses, "replay"
    truth = log_truth(contents, where)
    counts = write_bag(out, config, poses, log_imu(contents, where, config_toml), truth,
                       progress)
    topics = config.ros2_settings.recorded
    if truth:
        topics["truth"] = TRUTH_TOPIC
    return Exported(out, counts, poses_from, topics)

