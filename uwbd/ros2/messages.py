"""The ROS 2 messages of uwbd's poses and IMU samples, built with the pure-Python ``rosbags``
(the ``ros2`` and ``tools`` extras): the same for the live topics (:mod:`uwbd.ros2.publisher`)
and the bag (:mod:`uwbd.tools.ros2_bag`).

- the pose: ``geometry_msgs/msg/PoseWithCovarianceStamped`` in ``nav_frame_id`` with its 6×6
  covariance;
- odometry: ``nav_msgs/msg/Odometry``, the same pose, ``child_frame_id`` ``body_frame_id``,
  the twist the velocity in the body frame;
- the IMU: ``sensor_msgs/msg/Imu``, each sample in the sensor's own axes, frame
  ``<body_frame_id>_imu``;
- transforms: ``tf2_msgs/msg/TFMessage``, ``nav_frame_id`` → ``body_frame_id`` at each pose;
  the static ones ``body`` → ``body_imu`` (the mounting) and ``body`` → ``body_uwb`` (the
  lever arm);
- diagnostics: ``diagnostic_msgs/msg/DiagnosticArray``, a pose's health as one status
  ``uwbd: filter`` (level OK when healthy, WARN when not, STALE while waiting; the message
  the health's summary; values its phase, faults, notes, σ and protection levels);
- truth (bags only): ``geometry_msgs/msg/PoseStamped``.

Conventions. uwbd's body frame (forward-left-up) has its origin at the IMU (the pose is the
IMU's), so ``body → body_imu`` is the ``[imu] mounting`` rotation (sensor → body) with no
translation, and ``body → body_uwb`` the ``lever_arm_m`` translation (IMU → antenna, body
axes). The pose covariance orders x, y, z, then rotation about the navigation frame's x,
y, z, as ROS's fixed-axis convention does, so it is copied as it is. ROS puts an odometry
twist in the child frame: the ENU velocity is rotated into the body frame,
``v_b = R(q)ᵀ v_n``. uwbd's poses carry no velocity covariance and no angular rate, so the
twist's angular part is zero and its covariance is marked unknown (``covariance[0] = -1``);
fuse only its linear part, or use the pose. The IMU message has no orientation
(``orientation_covariance[0] = -1``); its rate and acceleration covariances are the
diagonal the filter assumes: the config's noise densities squared times the IMU's rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.stores import ros2_humble as msgs

from drivers.frames import ImuSample
from uwbd.config import Config
from uwbd.fusion.core.rotation import quat_from_matrix
from uwbd.fusion.types import Health, Phase, Pose

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
# hashes), so Humble's store serves every distribution.
TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
# each topic's type, by role (the roles of uwbd.config.ros2, and the bag's truth)
TYPES = {"pose": PoseWithCovarianceStamped.__msgtype__, "odom": Odometry.__msgtype__,
         "imu": Imu.__msgtype__, "tf": TFMessage.__msgtype__,
         "tf_static": TFMessage.__msgtype__, "diagnostics": DiagnosticArray.__msgtype__,
         "truth": PoseStamped.__msgtype__}
# unknown, as ROS marks it: uwbd's poses carry no velocity covariance, its IMU no orientation
TWIST_COVARIANCE = (-1.0,) + (0.0,) * 35
NO_ORIENTATION = (0.0, 0.0, 0.0, 1.0)
NO_ORIENTATION_COVARIANCE = (-1.0,) + (0.0,) * 8
IMU_SUFFIX = "_imu"  # the IMU's frame: <body_frame_id>_imu, the sensor's own axes
ANTENNA_SUFFIX = "_uwb"  # the UWB antenna's frame: <body_frame_id>_uwb


@dataclass(frozen=True)
class FrameIds:
    """The messages' frame names, from the config's ``[robot]`` section."""

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
    """The pose's ENU velocity in the body frame: ``R(q)ᵀ v_n``, the columns of
    :func:`~uwbd.fusion.core.rotation.quat_to_matrix` dotted with ``v_n`` (in plain floats:
    made at every pose, where numpy's arrays cost more than the sums)."""
    x, y, z, w = pose.orientation_xyzw
    a, b, c = pose.velocity_mps
    xx, yy, zz = 1 - 2 * (y * y + z * z), 1 - 2 * (x * x + z * z), 1 - 2 * (x * x + y * y)
    return (float(xx * a + 2 * (x * y + w * z) * b + 2 * (x * z - w * y) * c),
            float(2 * (x * y - w * z) * a + yy * b + 2 * (y * z + w * x) * c),
            float(2 * (x * z + w * y) * a + 2 * (y * z - w * x) * b + zz * c))


def pose_msg(pose: Pose, frames: FrameIds) -> PoseWithCovarianceStamped:
    return PoseWithCovarianceStamped(header=_header(pose.t_ns, frames.nav),
                                     pose=_pose_with_covariance(pose))


def odometry_msg(pose: Pose, frames: FrameIds) -> Odometry:
    return Odometry(
        header=_header(pose.t_ns, frames.nav), child_frame_id=frames.body,
        pose=_pose_with_covariance(pose),
        twist=TwistWithCovariance(twist=Twist(linear=_vector(body_velocity(pose)),
                                              angular=_vector((0.0, 0.0, 0.0))),
                                  covariance=np.array(TWIST_COVARIANCE)))


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


def imu_variances(config: Config, sample_times_ns: Sequence[int]) -> tuple[float, float]:
    """(gyro, accel) per-sample variances the filter assumes: noise density² × the IMU's
    rate (the median sample interval's inverse); zeros (unknown) under two samples."""
    if len(sample_times_ns) < 2:
        return 0.0, 0.0
    dt_ns = float(np.median(np.diff(sample_times_ns)))
    if dt_ns <= 0:
        return 0.0, 0.0
    rate_hz = 1e9 / dt_ns
    noise = config.filter_config().imu_noise
    return noise.gyro ** 2 * rate_hz, noise.acc ** 2 * rate_hz


def imu_msg(sample: ImuSample, frames: FrameIds, gyro_var: float = 0.0,
            acc_var: float = 0.0) -> Imu:
    return Imu(header=_header(sample.t_ns, frames.imu), orientation=_quat(NO_ORIENTATION),
               orientation_covariance=np.array(NO_ORIENTATION_COVARIANCE),
               angular_velocity=_vector(sample.gyro_rps),
               angular_velocity_covariance=np.array(_diagonal(gyro_var)),
               linear_acceleration=_vector(sample.acc_mps2),
               linear_acceleration_covariance=np.array(_diagonal(acc_var)))


def _diagonal(variance: float) -> tuple[float, ...]:
    return (variance, 0.0, 0.0, 0.0, variance, 0.0, 0.0, 0.0, variance)


# -- the numbers of each message, in its order (uwbd.ros2.cdr packs them) ---------------------


def pose_values(pose: Pose) -> tuple[float, ...]:
    return (*pose.position_m, *pose.orientation_xyzw, *pose.covariance)


def odometry_values(pose: Pose) -> tuple[float, ...]:
    return (*pose_values(pose), *body_velocity(pose), 0.0, 0.0, 0.0, *TWIST_COVARIANCE)


def tf_values(pose: Pose) -> tuple[float, ...]:
    return (*pose.position_m, *pose.orientation_xyzw)


def imu_values(sample: ImuSample, gyro_var: float, acc_var: float) -> tuple[float, ...]:
    return (*NO_ORIENTATION, *NO_ORIENTATION_COVARIANCE, *sample.gyro_rps,
            *_diagonal(gyro_var), *sample.acc_mps2, *_diagonal(acc_var))


def diagnostics_msg(t_ns: int, h: Health, hardware_id: str) -> DiagnosticArray:
    """A health record as ROS diagnostics (``diagnostic_msgs``' levels: 0 OK, 1 WARN,
    3 STALE)."""
    level = 0 if h.healthy else 3 if h.phase is Phase.WAITING else 1

    def text(x: float | None) -> str:
        return "" if x is None else f"{x:.4f}"
    values = [("phase", h.phase.value), ("faults", ",".join(h.faults)),
              ("notes", ",".join(h.notes)), ("position_sigma_m", text(h.position_sigma_m)),
              ("horizontal_protection_m", text(h.horizontal_protection_m)),
              ("vertical_protection_m", text(h.vertical_protection_m)),
              ("horizontal_available", str(h.horizontal_available).lower()),
              ("vertical_available", str(h.vertical_available).lower())]
    return DiagnosticArray(header=_header(t_ns, ""), status=[DiagnosticStatus(
        level=level, name="uwbd: filter", message=h.summary(),
        hardware_id=hardware_id, values=[KeyValue(key=k, value=v) for k, v in values])])


def truth_msg(truth: TruthPose, frames: FrameIds) -> PoseStamped:
    return PoseStamped(header=_header(truth.t_ns, frames.nav),
                       pose=_ros_pose(truth.position_m, truth.orientation_xyzw))

