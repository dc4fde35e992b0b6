"""``uwbd export --ros2``: a simulated run, replayed and exported by the real CLI, read back
with rosbags' own reader (a different typestore than the writer's, Jazzy's) and compared
with the log, message by message."""

from __future__ import annotations

import math
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from procs import one_line, uwbd
from rosbags.rosbag2 import Reader, WriterError
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from drivers.frames import ImuSample
from uwbd.config import parse
from uwbd.fusion.core.rotation import quat_to_matrix
from uwbd.fusion.types import Pose
from uwbd.logs.reading import read_log
from uwbd.tools.logtools import write_simulation
from uwbd.tools.ros2_bag import write_bag
from uwbd.tools.simulator import DEFAULT_SEGMENTS, SimConfig, simulate

READER_TYPES = get_typestore(Stores.ROS2_JAZZY)
TYPES = {
    "/uwbd/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/uwbd/odom": "nav_msgs/msg/Odometry",
    "/uwbd/imu": "sensor_msgs/msg/Imu",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/uwbd/truth": "geometry_msgs/msg/PoseStamped",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
TOL = 1e-9


class Bag:
    """A bag read back: topic -> its type, and its (bag timestamp, message) pairs."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.types: dict[str, str] = {}
        self.messages: dict[str, list[tuple[int, Any]]] = defaultdict(list)
        with Reader(path) as reader:
            for conn in reader.connections:
                self.types[conn.topic] = conn.msgtype
            for conn, t_ns, raw in reader.messages():
                self.messages[conn.topic].append(
                    (t_ns, READER_TYPES.deserialize_cdr(raw, conn.msgtype)))

    def msgs(self, topic: str) -> list[Any]:
        return [m for _, m in self.messages[topic]]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A short simulated run (raw bytes + truth, no poses) and its replay (raw, frames,
    poses; no truth), the replay made by the CLI."""
    folder = tmp_path_factory.mktemp("ros2")
    sim, replayed = folder / "s.mcap", folder / "r.mcap"
    write_simulation(simulate(SimConfig(seed=5, segments=DEFAULT_SEGMENTS[:4])), sim)
    # (wide alert limits, truth.WIDE_LIMITS: this layout is healthy under them)
    result = uwbd("replay", str(sim), "-o", str(replayed),
                  "--set", "fusion.horizontal_alert_limit_m=2.0",
                  "--set", "fusion.vertical_alert_limit_m=3.0")
    assert result.returncode == 0, result.stderr
    return sim, replayed


@pytest.fixture(scope="module")
def bag(logs: tuple[Path, Path]) -> Bag:
    """The replayed log exported: its own poses."""
    out = logs[1].parent / "bag"
    result = uwbd("export", str(logs[1]), "--ros2", str(out))
    assert result.returncode == 0, result.stderr
    assert "poses (the log's own)" in result.stdout, result.stdout
    return Bag(out)


@pytest.fixture(scope="module")
def tuned_bag(logs: tuple[Path, Path]) -> Bag:
    """The simulated log (no poses, truth) exported with another body frame name: replayed."""
    out = logs[0].parent / "tuned"
    result = uwbd("export", str(logs[0]), "--ros2", str(out),
                  "--set", "robot.body_frame_id=r1/base_link")
    assert result.returncode == 0, result.stderr
    assert "poses (replayed)" in result.stdout, result.stdout
    return Bag(out)


def log_json(path: Path, topic: str) -> list[dict[str, Any]]:
    return list(read_log(path).json(topic))


def xyzw(q: Any) -> list[float]:
    return [q.x, q.y, q.z, q.w]


def xyz(v: Any) -> list[float]:
    return [v.x, v.y, v.z]


def close(a: Any, b: Any, tol: float = TOL) -> bool:
    return bool(np.allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float),
                            rtol=0.0, atol=tol))


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def test_every_topic_is_there_with_its_type_and_count(logs: tuple[Path, Path], bag: Bag,
                                                      tuned_bag: Bag) -> None:
    replayed = read_log(logs[1])
    n_poses = sum(m.topic == "/pose" for m in replayed.messages)
    n_imu = sum(m.topic == "/imu" for m in replayed.messages)
    n_truth = sum(m.topic == "/truth" for m in read_log(logs[0]).messages)
    assert n_poses > 1000 and n_imu > 4000 and n_truth > 1000
    assert bag.types == TYPES  # the replayed log carries the source's truth
    assert tuned_bag.types == TYPES
    expected = {"/uwbd/pose": n_poses, "/uwbd/odom": n_poses, "/tf": n_poses,
                "/uwbd/imu": n_imu, "/tf_static": 1, "/uwbd/truth": n_truth,
                "/diagnostics": n_poses}
    assert {t: len(m) for t, m in tuned_bag.messages.items()} == expected
    # metadata.yaml, as `ros2 bag info` reads it: the storage, the file, each topic's count
    info = YAML(typ="safe").load((bag.path / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap" and info["version"] == 8
    (name,) = info["relative_file_paths"]
    assert name.endswith(".mcap") and (bag.path / name).is_file()
    listed = {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"], t["message_count"])
              for t in info["topics_with_message_count"]}
    assert listed == {t: (TYPES[t], expected[t]) for t in bag.types}
    assert info["message_count"] == sum(expected[t] for t in bag.types)
    static_qos = next(t["topic_metadata"]["offered_qos_profiles"]
                      for t in info["topics_with_message_count"]
                      if t["topic_metadata"]["name"] == "/tf_static")
    assert "durability: 1" in static_qos  # transient local: `ros2 bag play` latches it
    # messages in time order, stamped with the log's times
    times = [t for msgs in bag.messages.values() for t, _ in msgs]
    assert min(times) == info["starting_time"]["nanoseconds_since_epoch"]


def test_poses_equal_the_logs(logs: tuple[Path, Path], bag: Bag, tuned_bag: Bag) -> None:
    source = log_json(logs[1], "/pose")
    for exported in (bag, tuned_bag):  # the log's own poses; a replay of the raw log
        pairs = exported.messages["/uwbd/pose"]
        assert len(pairs) == len(source)
        for (t_ns, msg), d in zip(pairs, source, strict=True):
            assert t_ns == d["t_ns"] == stamp_ns(msg.header)
            assert msg.header.frame_id == "enu"
            p = d["pose"]["position"]
            assert close(xyz(msg.pose.pose.position), [p["x"], p["y"], p["z"]])
            q = d["pose"]["orientation"]
            assert close(xyzw(msg.pose.pose.orientation), [q["x"], q["y"], q["z"], q["w"]])
            assert close(msg.pose.covariance, d["covariance"])
        tf = exported.msgs("/tf")
        assert [stamp_ns(m.transforms[0].header) for m in tf] == [d["t_ns"] for d in source]
        last, d = tf[-1].transforms[0], source[-1]
        assert close(xyz(last.transform.translation), list(d["pose"]["position"].values()))


def test_diagnostics_carry_each_poses_health(logs: tuple[Path, Path], bag: Bag) -> None:
    """One DiagnosticArray a pose: OK exactly when the log's pose said healthy, the summary
    as its message, the phase, faults and protection levels as its values."""
    source = log_json(logs[1], "/pose")
    pairs = bag.messages["/diagnostics"]
    assert len(pairs) == len(source)
    levels = set()
    for (t_ns, msg), d in zip(pairs, source, strict=True):
        (status,) = msg.status
        assert t_ns == d["t_ns"] == stamp_ns(msg.header) and status.name == "uwbd: filter"
        health = d["health"]
        assert (status.level == 0) == health["healthy"] and status.message == d["status"]
        values = {kv.key: kv.value for kv in status.values}
        assert values["phase"] == health["phase"]
        assert values["faults"] == ",".join(health["faults"])
        for key in ("horizontal_protection_m", "vertical_protection_m"):
            if health.get(key) is None:  # (not known: while the bank warms up)
                assert values[key] == ""
            else:
                assert float(values[key]) == pytest.approx(health[key], abs=1e-4)
        for key in ("horizontal_available", "vertical_available"):
            assert values[key] == str(health[key]).lower()
        levels.add(status.level)
    assert 0 in levels  # (and the run is long enough to be healthy)


def test_odometry_twist_is_the_velocity_in_the_body_frame(logs: tuple[Path, Path],
                                                          bag: Bag) -> None:
    source = log_json(logs[1], "/pose")
    odom = bag.msgs("/uwbd/odom")
    moving = 0
    for msg, d in zip(odom, source, strict=True):
        assert msg.header.frame_id == "enu" and msg.child_frame_id == "base_link"
        assert stamp_ns(msg.header) == d["t_ns"]
        assert close(msg.pose.covariance, d["covariance"])
        q = msg.pose.pose.orientation
        R = quat_to_matrix(np.array([q.w, q.x, q.y, q.z]))  # body -> ENU
        v_body = np.array(xyz(msg.twist.twist.linear))
        assert close(R @ v_body, d["velocity_mps"])
        assert xyz(msg.twist.twist.angular) == [0.0, 0.0, 0.0]
        assert msg.twist.covariance[0] == -1.0  # unknown: poses carry no velocity covariance
        moving += bool(np.linalg.norm(v_body) > 0.5)
    assert moving > 100  # the rotation was exercised on a moving vehicle
    # forward-left-up: a ground vehicle driving forward has most of its speed on body x
    fast = [m for m in odom if np.linalg.norm(xyz(m.twist.twist.linear)) > 1.0]
    assert fast and all(m.twist.twist.linear.x > 0.9 * np.linalg.norm(
        xyz(m.twist.twist.linear)) for m in fast)


def test_imu_is_the_logs_frames_in_the_sensor_axes(logs: tuple[Path, Path],
                                                   bag: Bag) -> None:
    source = log_json(logs[1], "/imu")
    imu = bag.messages["/uwbd/imu"]
    assert len(imu) == len(source)
    for (t_ns, msg), d in zip(imu, source, strict=True):
        assert t_ns == d["t_ns"] == stamp_ns(msg.header)
        assert msg.header.frame_id == "base_link_imu"
        assert xyz(msg.angular_velocity) == d["gyro_rps"]
        assert xyz(msg.linear_acceleration) == d["acc_mps2"]
        assert msg.orientation_covariance[0] == -1.0
    # the covariances the filter assumes: density² × rate (200 Hz: the rate as the sample
    # times say it, which a batched read's spread makes good to a percent), on the diagonal
    config = parse(read_log(logs[1]).metadata["config_toml"])
    noise = config.filter_config().imu_noise
    first = imu[0][1]
    np.testing.assert_allclose(np.reshape(first.angular_velocity_covariance, (3, 3)),
                               np.eye(3) * noise.gyro ** 2 * 200.0, rtol=1e-2, atol=0.0)
    np.testing.assert_allclose(np.reshape(first.linear_acceleration_covariance, (3, 3)),
                               np.eye(3) * noise.acc ** 2 * 200.0, rtol=1e-2, atol=0.0)
    # the static transform is the mounting (sensor -> body) and the lever arm
    (static,) = bag.msgs("/tf_static")
    by_child = {t.child_frame_id: t for t in static.transforms}
    assert set(by_child) == {"base_link_imu", "base_link_uwb"}
    assert all(t.header.frame_id == "base_link" for t in static.transforms)
    q = by_child["base_link_imu"].transform.rotation
    C_bs = quat_to_matrix(np.array([q.w, q.x, q.y, q.z]))
    assert close(C_bs, config.mounting, 1e-12)
    assert xyz(by_child["base_link_imu"].transform.translation) == [0.0, 0.0, 0.0]
    assert close(xyz(by_child["base_link_uwb"].transform.translation), config.lever_arm_m)
    # at the still start the accelerometer, taken into the body frame by it, reads +g up
    acc_body = C_bs @ np.mean([xyz(m.linear_acceleration) for _, m in imu[:50]], axis=0)
    assert close(acc_body, [0.0, 0.0, 9.81], 0.3), acc_body


def test_frame_names_come_from_the_config(tuned_bag: Bag) -> None:
    (tf0,) = tuned_bag.msgs("/tf")[0].transforms
    assert (tf0.header.frame_id, tf0.child_frame_id) == ("enu", "r1/base_link")
    assert {m.child_frame_id for m in tuned_bag.msgs("/uwbd/odom")} == {"r1/base_link"}
    assert {m.header.frame_id for m in tuned_bag.msgs("/uwbd/imu")} == {"r1/base_link_imu"}
    (static,) = tuned_bag.msgs("/tf_static")
    assert {(t.header.frame_id, t.child_frame_id) for t in static.transforms} == {
        ("r1/base_link", "r1/base_link_imu"), ("r1/base_link", "r1/base_link_uwb")}


def test_truth_is_exported(logs: tuple[Path, Path], tuned_bag: Bag) -> None:
    source = log_json(logs[0], "/truth")
    truth = tuned_bag.messages["/uwbd/truth"]
    assert len(truth) == len(source)
    for (t_ns, msg), d in zip(truth, source, strict=True):
        assert t_ns == d["t_ns"] == stamp_ns(msg.header) and msg.header.frame_id == "enu"
        assert close(xyz(msg.pose.position), list(d["pose"]["position"].values()))
        o = d["pose"]["orientation"]
        assert close(xyzw(msg.pose.orientation), [o["x"], o["y"], o["z"], o["w"]])
        assert math.isclose(sum(v * v for v in xyzw(msg.pose.orientation)), 1.0)


def test_errors_are_one_line_before_any_work(tmp_path: Path, logs: tuple[Path, Path],
                                             bag: Bag) -> None:
    before = sorted(p.name for p in bag.path.iterdir())
    one_line(uwbd("export", str(logs[1]), "--ros2", str(bag.path)), 2, str(bag.path), "exists")
    assert sorted(p.name for p in bag.path.iterdir()) == before  # left alone
    text = tmp_path / "notes.txt"
    text.write_text("not a log\n")
    out = tmp_path / "out"
    one_line(uwbd("export", str(text), "--ros2", str(out)), 2, str(text), "not an MCAP file")
    one_line(uwbd("export", str(tmp_path / "nope.mcap"), "--ros2", str(out)), 2, "nope.mcap")
    one_line(uwbd("export", str(logs[1]), "--ros2", str(tmp_path / "no" / "bag")), 2,
             "does not exist")
    one_line(uwbd("export", str(logs[1]), "--ros2", str(out), "--set", "fusion.bogus=1"), 2,
             "fusion.bogus")
    assert not out.exists()


def test_transforms_follow_the_ros_conventions(tmp_path: Path) -> None:
    """With rotations that are not their own inverse (the simulator's mounting, 180° about
    x, is): the static transform maps sensor vectors into the body, the odometry twist is
    the ENU velocity in the body frame."""
    config = parse('[robot]\nbody_frame_id = "b"\nnav_frame_id = "map"\n[imu]\n'
                   "mounting = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]\n"
                   "lever_arm_m = [0.1, 0.2, 0.3]\n")
    s = math.sqrt(0.5)
    heading_north = Pose(  # body x (forward) along ENU y (north): yaw +90°
        t_ns=1_700_000_000_123_456_789, position_m=(1.0, 2.0, 3.0), velocity_mps=(0.0, 2.0, 0.0),
        orientation_xyzw=(0.0, 0.0, s, s), covariance=tuple(float(i) for i in range(36)),
        status="tracking", heading_observable=True)
    sample = ImuSample(heading_north.t_ns, (9.81, 0.0, 0.0), (0.0, 0.0, 0.5))
    counts = write_bag(tmp_path / "b", config, [heading_north], [sample])
    assert counts == {"/tf_static": 1, "/uwbd/pose": 1, "/uwbd/odom": 1, "/tf": 1,
                      "/uwbd/imu": 1, "/diagnostics": 1}
    bag = Bag(tmp_path / "b")
    (odom,) = bag.msgs("/uwbd/odom")
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "b")
    assert close(xyz(odom.twist.twist.linear), [2.0, 0.0, 0.0])  # straight ahead
    assert (odom.header.stamp.sec, odom.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert list(odom.pose.covariance) == list(heading_north.covariance)
    (static,) = bag.msgs("/tf_static")
    imu_tf = next(t for t in static.transforms if t.child_frame_id == "b_imu")
    q = imu_tf.transform.rotation
    R = quat_to_matrix(np.array([q.w, q.x, q.y, q.z]))  # p_parent = R p_child
    (imu,) = bag.msgs("/uwbd/imu")
    assert imu.header.frame_id == "b_imu"
    # the sensor's x axis is the body's left (y) axis under this mounting
    assert close(R @ np.array(xyz(imu.linear_acceleration)), [0.0, 9.81, 0.0], 1e-12)
    assert close(R, config.mounting, 1e-12)
    assert list(imu.angular_velocity_covariance) == [0.0] * 9  # one sample: rate unknown
    with pytest.raises(WriterError):  # never over an existing bag
        write_bag(tmp_path / "b", config, [heading_north], [sample])
    assert Bag(tmp_path / "b").types  # still whole


def test_without_the_tools_extra_export_says_how_to_get_it(tmp_path: Path,
                                                            logs: tuple[Path, Path]) -> None:
    (tmp_path / "sitecustomize.py").write_text(
        "import importlib.abc, sys\n\n"
        "class NotInstalled(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'rosbags':\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n\n"
        "sys.meta_path.insert(0, NotInstalled())\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = tmp_path / "bag"
    one_line(uwbd("export", str(logs[1]), "--ros2", str(out), env=env), 2,
             "export needs the tools extra", "rosbags", "pip install 'uwbd[tools]'")
    assert not out.exists()
