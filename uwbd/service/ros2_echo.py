"""``uwbd echo --ros2 [TOPIC]``: what a ROS 2 subscriber would get from the daemon's live
topics, decoded without ROS 2: each sample on ``<domain>/<topic>/<any type>/<any hash>``,
its type read from the key, the CDR payload decoded by rosbags, the rmw_zenoh attachment
checked (a sample without a well-formed one is said to be one ROS 2 drops). When nothing
arrives it lists the ROS 2 publishers it sees on the domain (their liveliness tokens).
"""

from __future__ import annotations

import math
from typing import Any

import zenoh

from uwbd import journal
from uwbd.config.ros2 import Ros2Settings
from uwbd.ros2 import rmw_zenoh as rz
from uwbd.ros2.messages import TYPESTORE
from uwbd.service.echo import QUIET_AFTER_S, Listen

LOG = journal.get("echo")


def ros_type(dds_type: str) -> str:
    """``geometry_msgs::msg::dds_::Pose_`` → ``geometry_msgs/msg/Pose``."""
    package, kind, _, name = dds_type.split("::")
    return f"{package}/{kind}/{name.removesuffix('_')}"


def _xyz(v: Any) -> str:
    return f"({v.x:.3f}, {v.y:.3f}, {v.z:.3f})"


def _xyzw(q: Any) -> str:
    return f"({q.x:.3f}, {q.y:.3f}, {q.z:.3f}, {q.w:.3f})"


def summary(msgtype: str, msg: Any) -> str:
    """One line of a decoded message: the parts a user checks."""
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        c = msg.pose.covariance
        return (f"{msg.header.frame_id}  p={_xyz(msg.pose.pose.position)} m  "
                f"q={_xyzw(msg.pose.pose.orientation)}  σxy={math.sqrt(max(c[0] + c[7], 0)):.3f} m")
    if msgtype == "nav_msgs/msg/Odometry":
        return (f"{msg.header.frame_id}→{msg.child_frame_id}  p={_xyz(msg.pose.pose.position)} "
                f"m  v_body={_xyz(msg.twist.twist.linear)} m/s")
    if msgtype == "tf2_msgs/msg/TFMessage":
        return "  ".join(f"{t.header.frame_id}→{t.child_frame_id} t={_xyz(t.transform.translation)}"
                         f" q={_xyzw(t.transform.rotation)}" for t in msg.transforms)
    if msgtype == "sensor_msgs/msg/Imu":
        return (f"{msg.header.frame_id}  gyro={_xyz(msg.angular_velocity)} rad/s  "
                f"acc={_xyz(msg.linear_acceleration)} m/s²")
    if msgtype == "diagnostic_msgs/msg/DiagnosticArray":
        levels = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
        return "  ".join(f"{levels.get(int(s.level), s.level)} {s.name}: {s.message}"
                         for s in msg.status)
    return repr(msg)[:200]


def _stamp(msg: Any) -> str:
    header = getattr(msg, "header", None)
    if header is None:
        transforms = getattr(msg, "transforms", None)
        header = transforms[0].header if transforms else None
    if header is None:
        return "-"
    return f"{header.stamp.sec}.{header.stamp.nanosec:09d}"


def line(key: str, payload: bytes, attachment: bytes | None) -> str:
    """A sample as a line: topic, sequence number, stamp, summary; or what is wrong."""
    parts = key.split("/")
    topic = "/" + "/".join(parts[1:-2])
    try:
        msgtype = ros_type(parts[-2])
    except ValueError:
        return f"{topic}  (not an rmw_zenoh key: {key})"
    try:
        seq = f"#{rz.read_attachment(attachment)[0]}" if attachment is not None else None
    except ValueError as err:
        seq = None
        LOG.debug("%s: %s", key, err)
    if seq is None:
        return f"{topic}  (no rmw_zenoh attachment: a ROS 2 subscriber drops this sample)"
    try:
        msg = TYPESTORE.deserialize_cdr(payload, msgtype)
    except Exception as err:
        return f"{topic} {seq}  (not a {msgtype}: {type(err).__name__}: {err})"
    return f"{topic} {seq}  {_stamp(msg)}  {summary(msgtype, msg)}"


def publishers_seen(session: zenoh.Session, domain_id: int) -> list[str]:
    """``<topic> (<node>)`` of each ROS 2 publisher whose token is visible on the domain."""
    out = set()
    for reply in session.liveliness().get(f"{rz.ADMIN_SPACE}/{domain_id}/**", timeout=1.0):
        if reply.ok is None:
            continue
        parts = str(reply.ok.key_expr).split("/")
        if len(parts) >= 13 and parts[5] == rz.PUBLISHER:
            node = f"{parts[7].replace(rz.SLASH_REPLACEMENT, '/').rstrip('/')}/{parts[8]}"
            out.add(f"{parts[9].replace(rz.SLASH_REPLACEMENT, '/')} ({node})")
    return sorted(out)


def ros2_topic(settings: Ros2Settings, topic: str) -> Listen:
    """Subscribe to ``topic`` (a name as ``[ros2]`` takes it, resolved in its namespace) on
    the settings' domain, whatever its type and hash."""
    name = settings.resolve(topic)
    key = f"{settings.domain_id}/{name.strip('/')}/*/*"

    def quiet(session: zenoh.Session, where: str) -> None:
        seen = publishers_seen(session, settings.domain_id)
        if seen:
            LOG.warning("nothing on %s for %.0f s; ROS 2 publishers seen on domain %d: %s",
                        name, QUIET_AFTER_S, settings.domain_id, ", ".join(seen))
        else:
            LOG.warning("nothing on %s for %.0f s, and no ROS 2 publisher seen on domain %d "
                        "via %s: is the daemon running with [ros2] enabled, on this domain "
                        "(ROS_DOMAIN_ID)?", name, QUIET_AFTER_S, settings.domain_id, where)
    return Listen(key, line, quiet, history=True)
