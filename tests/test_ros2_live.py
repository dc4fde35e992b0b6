"""The daemon's ROS 2 topics over rmw_zenoh, held to the specification (ros2/rmw_zenoh's
docs/design.md) with real Zenoh sessions on a unix socket: the grammar against the design
document's worked examples byte for byte, then a real `uwbd run` fed by the emulator, seen
from a router session as a ROS 2 node would see it, and `uwbd echo --ros2`. There is no ROS 2
on this machine: what needs one to confirm is said in docs/ros2.md."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
import zenoh
import zenoh.ext
from emulated import emulated_sources
from hypothesis import given, settings
from hypothesis import strategies as st
from procs import one_line, uwbd
from rosbags.typesys import Stores, get_typestore

from drivers.emulator import DeviceSpec, Emulator, Faults
from drivers.emulator.scenario import CircleScenario
from drivers.frames import ImuSample
from uwbd.config import ConfigError, parse
from uwbd.config.ros2 import settings_of
from uwbd.fusion.types import Pose
from uwbd.ros2 import rmw_zenoh as rz
from uwbd.ros2.cdr import imu_layout, pose_layouts
from uwbd.ros2.messages import (
    TYPESTORE,
    FrameIds,
    imu_msg,
    imu_values,
    odometry_msg,
    pose_msg,
    tf_msg,
)
from uwbd.tools.ros2_bag import write_bag

# a store of its own (Jazzy's), not uwbd's: the hashes and the decoding are checked against it
JAZZY = get_typestore(Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
TYPES = {"/uwbd/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
         "/uwbd/odom": "nav_msgs/msg/Odometry", "/uwbd/imu": "sensor_msgs/msg/Imu",
         "/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
         "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
UWBD = [sys.executable, "-m", "uwbd"]
# a whole config but for its [ros2] and [zenoh]: an IMU and a tag that reports its anchors
SOURCES = ('[[sources]]\nname = "imu"\ndriver = "wit"\nport = "/dev/ttyUSB0"\n'
           '[[sources]]\nname = "uwb"\ndriver = "dwm1001"\nport = "/dev/ttyACM0"\n')


# -- the grammar, against design.md's examples -----------------------------------------------


def test_topic_keys_are_the_design_documents_examples() -> None:
    """"Topic and Service name mapping to Zenoh key expressions": `chatter`, and `chatter`
    in the namespace `/robot1`."""
    assert JAZZY.hash_rihs01("std_msgs/msg/String") == STRING_HASH
    dds = rz.dds_type_name("std_msgs/msg/String")
    assert dds == "std_msgs::msg::dds_::String_"
    plain = settings_of({}, env={})
    assert rz.topic_key(0, plain.resolve("chatter"), dds, STRING_HASH) == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    robot1 = settings_of({"namespace": "/robot1"}, env={})
    assert rz.topic_key(0, robot1.resolve("chatter"), dds, STRING_HASH) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    assert robot1.resolve("/tf") == "/tf" and robot1.resolve("~/imu") == "/robot1/uwbd/imu"


def test_liveliness_tokens_are_the_design_documents_examples() -> None:
    """"Graph Cache": the `listener` node and the `talker` node's publisher (depth 7)."""
    assert rz.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")
    assert rz.publisher_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "/", "talker",
                              "/chatter", "std_msgs::msg::dds_::String_", STRING_HASH,
                              rz.Qos(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    # the listener's subscription in the same section writes depth 10 the same way
    assert rz.Qos(depth=10).keyexpr() == "::,10:,:,:,,"
    # transient local (1) and depth 1, as /tf_static's; the defaults write nothing
    assert rz.Qos(durability=rz.TRANSIENT_LOCAL, depth=1).keyexpr() == ":1:,1:,:,:,,"
    assert rz.Qos(rz.BEST_EFFORT, rz.VOLATILE, rz.KEEP_ALL, 42).keyexpr() == "2::2,:,:,:,,"


def test_gid_and_attachment_are_laid_out_as_rmw_zenoh_lays_them() -> None:
    """The GID: XXH3-128 of the token, low 64 bits then high, little-endian (xxHash's
    reference value of the empty input); the attachment: 33 bytes ("Publishers")."""
    assert rz.gid("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    token = "@ros2_lv/0/x/0/1/MP/%/%/uwbd/%uwbd%pose/t/h/::,10:,:,:,,"
    gid = rz.gid(token)
    assert len(gid) == 16 and gid == rz.gid(token)
    data = rz.attachment(1, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33
    assert data[:8] == (1).to_bytes(8, "little") and data[16] == 16 and data[17:] == gid
    assert int.from_bytes(data[8:16], "little") == 1_700_000_000_123_456_789
    assert rz.read_attachment(data) == (1, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="33 bytes"):
        rz.read_attachment(data[:-1])


@pytest.mark.parametrize(("seq", "t_ns"), [(1, 1_700_000_000_123_456_789), (2**63 - 1, 0),
                                           (12345, 2**62 + 7)])
def test_the_attachment_is_what_zenoh_ext_serializes(seq: int, t_ns: int) -> None:
    """rmw_zenoh (Humble 0.1.2, Jazzy 0.2.4, Rolling 0.6.0 and later) writes its attachment
    with zenoh-ext's serializer, as ``(int64 sequence number, int64 source timestamp,
    [uint8; 16] gid)``: held here to that serializer itself, both ways, not to uwbd's
    reading of the design document."""
    gid = rz.gid(f"@ros2_lv/0/z/0/{seq % 97}/MP/%/%/uwbd/%uwbd%pose/t/h/::,10:,:,:,,")
    ours = rz.attachment(seq, t_ns, gid)
    theirs = zenoh.ext.z_serialize((zenoh.ext.Int64(seq), zenoh.ext.Int64(t_ns),
                                    [zenoh.ext.UInt8(b) for b in gid]))
    assert ours == theirs.to_bytes()
    back = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64,
                                         list[zenoh.ext.UInt8]], zenoh.ZBytes(ours))
    assert (int(back[0]), int(back[1]), bytes(int(b) for b in back[2])) == (seq, t_ns, gid)


# -- the [ros2] section ------------------------------------------------------------------------


@pytest.mark.parametrize(("extra", "needles"), [
    ('[ros2]\nenabled = true\n[zenoh]\nenabled = false\n', ("ros2.enabled", "zenoh.enabled")),
    ('[ros2]\nnamespace = "robot 1"\n', ("ros2.namespace", "ROS 2 namespace")),
    ('[ros2]\npose_topic = "uwbd//pose"\n', ("ros2.pose_topic", "ROS 2 topic name")),
    ('[ros2]\nnode_name = "1uwbd"\n', ("ros2.node_name", "node name")),
    ('[ros2]\ndomain_id = 300\n', ("ros2.domain_id", "at most 232")),
    ('[ros2]\ndistro = "foxy"\n', ("ros2.distro", "humble")),
    ('[ros2]\nodom_topic = "/tf"\n', ("ros2.tf_topic", "ros2.odom_topic", "its own name")),
])
def test_a_bad_ros2_section_names_its_key(extra: str, needles: tuple[str, ...]) -> None:
    with pytest.raises(ConfigError) as err:
        parse(SOURCES + extra)
    text = str(err.value)
    for needle in needles:
        assert needle in text, text


def test_the_imu_topic_is_live_only_when_named_and_always_in_a_bag() -> None:
    """#44: the IMU republished costs most of the publishers' CPU: off live by default, on
    when the section names it; a bag of a log holds it by default all the same, and
    ``imu_topic = ""`` turns it off in both."""
    default = settings_of({"enabled": True}, env={})
    assert "imu" not in default.published and default.published["pose"] == "/uwbd/pose"
    assert default.recorded["imu"] == "/uwbd/imu"
    named = settings_of({"enabled": True, "imu_topic": "sensors/imu"}, env={})
    assert named.published["imu"] == named.recorded["imu"] == "/sensors/imu"
    off = settings_of({"enabled": True, "imu_topic": ""}, env={})
    assert "imu" not in off.published and "imu" not in off.recorded


def test_domain_comes_from_the_section_then_ros_domain_id() -> None:
    assert settings_of({"domain_id": 7}, env={"ROS_DOMAIN_ID": "3"}).domain_id == 7
    from_env = settings_of({}, env={"ROS_DOMAIN_ID": "3"})
    assert (from_env.domain_id, from_env.domain_from) == (3, "ROS_DOMAIN_ID")
    assert settings_of({}, env={"ROS_DOMAIN_ID": "x"}).domain_id == 0


def test_the_bag_takes_the_sections_names(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader  # noqa: PLC0415

    config = parse('[ros2]\nnamespace = "/r1"\npose_topic = "pose"\nimu_topic = ""\n'
                   'diagnostics_topic = "~/health"\n')
    counts = write_bag(tmp_path / "b", config, [], [ImuSample(1, (0, 0, 9.8), (0, 0, 0))])
    with Reader(tmp_path / "b") as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
    assert topics == {"/r1/pose": TYPES["/uwbd/pose"], "/r1/uwbd/odom": TYPES["/uwbd/odom"],
                      "/tf": TYPES["/tf"], "/tf_static": TYPES["/tf_static"],
                      "/r1/uwbd/health": TYPES["/diagnostics"]}
    assert counts["/tf_static"] == 1 and counts["/r1/pose"] == 0


def _blocked(tmp_path: Path, module: str) -> dict[str, str]:
    """An environment in which ``module`` is not installed."""
    (tmp_path / "sitecustomize.py").write_text(
        "import importlib.abc, sys\n\n"
        "class NotInstalled(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] == {module!r}:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n\n"
        "sys.meta_path.insert(0, NotInstalled())\n")
    return {**os.environ, "PYTHONPATH": str(tmp_path)}


def test_without_the_ros2_extra_the_section_is_refused_in_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(SOURCES + '[zenoh]\nmulticast_scouting = false\n[ros2]\nenabled = true\n')
    env = _blocked(tmp_path, "xxhash")
    one_line(uwbd("check-config", str(cfg), env=env), 2, "ros2.enabled", "xxhash",
             "pip install 'uwbd[ros2]'")
    one_line(uwbd("run", "-c", str(cfg), "--log-dir", str(tmp_path / "logs"), env=env), 2,
             "ros2.enabled", "the ros2 extra")
    assert not (tmp_path / "logs").exists() or not any((tmp_path / "logs").iterdir())
    one_line(uwbd("echo", "--ros2", "--connect", "tcp/127.0.0.1:9", "--timeout", "1",
                  env=_blocked(tmp_path, "rosbags")), 2, "echo --ros2 needs the ros2 extra")


# -- a daemon, as ROS 2 sees it ----------------------------------------------------------------


def _router(sock: Path) -> zenoh.Session:
    """A router on the socket, as rmw_zenohd is to ROS 2 nodes: up before the daemon, so its
    subscribers see every sample from the first."""
    return zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "router", "listen": {"endpoints": [f"unixsock-stream/{sock}"]},
        "scouting": {"multicast": {"enabled": False}}})))


def _config(tmp: Path, ports: dict[str, str], sock: Path) -> Path:
    path = tmp / "cfg.toml"
    path.write_text(f"""
{emulated_sources(ports)}
[zenoh]
prefix = "uwbd/test"
connect = ["unixsock-stream/{sock}"]
multicast_scouting = false

[ros2]
enabled = true
imu_topic = "uwbd/imu"  # (off live unless named: every topic is checked here)
""")
    return path


class Seen:
    """Everything the router's subscribers got: per key, (payload, attachment) in order."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[bytes, bytes | None]]] = defaultdict(list)
        self.json_poses: list[dict[str, Any]] = []

    def ros(self, sample: zenoh.Sample) -> None:
        att = None if sample.attachment is None else sample.attachment.to_bytes()
        self.samples[str(sample.key_expr)].append((sample.payload.to_bytes(), att))

    def pose(self, sample: zenoh.Sample) -> None:
        self.json_poses.append(json.loads(sample.payload.to_bytes()))


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """`uwbd run` with [ros2] on, the emulator feeding it for 12 s (past the echoes), a
    router subscribed to everything; `uwbd echo --ros2` and a late transient-local
    subscriber beside it."""
    tmp = tmp_path_factory.mktemp("ros2live")
    sock = tmp / "router.sock"
    router = _router(sock)
    seen = Seen()
    subs = [router.declare_subscriber("0/**", seen.ros),
            router.declare_subscriber("uwbd/test/pose", seen.pose)]
    devices = [DeviceSpec("imu", "wit", Faults(split=True)), DeviceSpec("uwb", "nlink")]
    out: dict[str, Any] = {"seen": seen}
    with Emulator(devices, CircleScenario(seed=4), duration_s=12.0, link_dir=tmp) as emu:
        cfg = _config(tmp, {n: p.path for n, p in emu.ports.items()}, sock)
        daemon = subprocess.Popen([*UWBD, "run", "-c", str(cfg), "--log-dir", str(tmp / "logs")],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 20
            while not any(k.startswith("0/tf_static/") for k in seen.samples):
                assert time.monotonic() < deadline and daemon.poll() is None, "no /tf_static"
                time.sleep(0.05)
            emu.start()
            deadline = time.monotonic() + 15
            while len(seen.json_poses) < 150 and time.monotonic() < deadline:
                time.sleep(0.1)
            out["tokens"] = sorted(str(r.ok.key_expr) for r in
                                   router.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                                   if r.ok is not None)
            out["daemon_zid"] = [str(z) for z in router.info.peers_zid()]
            late: list[bytes] = []
            late_sub = zenoh.ext.declare_advanced_subscriber(
                router, "0/tf_static/**", lambda s: late.append(s.payload.to_bytes()),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1))
            time.sleep(1.0)
            late_sub.undeclare()
            out["late_tf_static"] = late
            out["echo"] = subprocess.run(
                [*UWBD, "echo", "--ros2", "--connect", f"unixsock-stream/{sock}", "--count", "3",
                 "--timeout", "10"], capture_output=True, text=True, timeout=30, check=False)
            out["echo_static"] = subprocess.run(
                [*UWBD, "echo", "--ros2", "/tf_static", "--connect", f"unixsock-stream/{sock}",
                 "--count", "1", "--timeout", "10"], capture_output=True, text=True, timeout=30,
                check=False)
            status = [json.loads(r.ok.payload.to_bytes())
                      for r in router.get("uwbd/test/status", timeout=2.0) if r.ok is not None]
            out["status"] = status[0] if status else {}
        finally:
            daemon.send_signal(signal.SIGINT)
            _, err = daemon.communicate(timeout=30)
            for sub in subs:
                sub.undeclare()
            out["after"] = sorted(str(r.ok.key_expr) for r in
                                  router.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                                  if r.ok is not None)
            router.close()
    out["returncode"], out["stderr"] = daemon.returncode, err.decode()
    return out


def _by_topic(seen: Seen) -> dict[str, tuple[str, list[tuple[bytes, bytes | None]]]]:
    """Topic → (its key, its samples)."""
    out = {}
    for key, samples in seen.samples.items():
        out["/" + "/".join(key.split("/")[1:-2])] = (key, samples)
    return out


def test_each_topic_is_on_its_key_with_its_type_and_hash(live: dict[str, Any]) -> None:
    assert live["returncode"] == 0, live["stderr"]
    topics = _by_topic(live["seen"])
    assert set(topics) == set(TYPES)
    for topic, (key, samples) in topics.items():
        msgtype = TYPES[topic]
        assert key == rz.topic_key(0, topic, rz.dds_type_name(msgtype),
                                   JAZZY.hash_rihs01(msgtype)), key
        assert samples, topic
        for payload, _ in samples[:5]:
            assert payload[:4] == b"\x00\x01\x00\x00"  # CDR, little-endian
            JAZZY.deserialize_cdr(payload, msgtype)
    imu = [JAZZY.deserialize_cdr(p, TYPES["/uwbd/imu"]).header.stamp
           for p, _ in topics["/uwbd/imu"][1]]
    stamps = [s.sec * 1_000_000_000 + s.nanosec for s in imu]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)  # held, in order
    n = {t: len(s) for t, (_, s) in topics.items()}
    assert n["/tf_static"] == 1 and n["/uwbd/pose"] == n["/uwbd/odom"] == n["/tf"] > 150
    assert n["/uwbd/imu"] > 3 * n["/uwbd/pose"] and n["/diagnostics"] >= 3


def test_every_sample_carries_a_well_formed_attachment(live: dict[str, Any]) -> None:
    """Sequence numbers from 1, one more each sample (nothing lost on a socket); the source
    time the wall clock; one GID per publisher: XXH3-128 of its liveliness token."""
    tokens = {t.split("/")[9].replace("%", "/"): t for t in live["tokens"]
              if t.split("/")[5] == "MP"}
    now = time.time_ns()
    for topic, (_, samples) in _by_topic(live["seen"]).items():
        parsed = [rz.read_attachment(att) for _, att in samples if att is not None]
        assert len(parsed) == len(samples), topic
        assert [seq for seq, _, _ in parsed] == list(range(1, len(samples) + 1)), topic
        assert {gid for _, _, gid in parsed} == {
            xxhash.xxh3_128_intdigest(tokens[topic].encode()).to_bytes(16, "little")}
        assert all(now - 120e9 < t_ns <= now for _, t_ns, _ in parsed)


def test_the_ros_pose_is_the_json_pose(live: dict[str, Any]) -> None:
    """Every PoseWithCovarianceStamped decodes (rosbags, Jazzy) to the pose, covariance and
    stamp of the same pose on uwbd's JSON key, within 1e-9."""
    json_poses = {p["t_ns"]: p for p in live["seen"].json_poses}
    _, samples = _by_topic(live["seen"])["/uwbd/pose"]
    matched = 0
    for payload, _ in samples:
        msg = JAZZY.deserialize_cdr(payload, TYPES["/uwbd/pose"])
        t_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if t_ns not in json_poses:
            continue  # a JSON pose the router got after it stopped listening
        j = json_poses[t_ns]
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        assert msg.header.frame_id == j["frame_id"] == "enu"
        assert np.allclose([p.x, p.y, p.z], list(j["pose"]["position"].values()), atol=1e-9)
        assert np.allclose([q.x, q.y, q.z, q.w], list(j["pose"]["orientation"].values()),
                           atol=1e-9)
        assert np.allclose(msg.pose.covariance, j["covariance"], atol=1e-9)
        matched += 1
    assert matched >= 0.95 * len(samples) > 140


def test_the_graph_shows_the_node_and_its_publishers_and_forgets_them(
        live: dict[str, Any]) -> None:
    (zid,) = live["daemon_zid"]
    node = rz.node_token(0, zid, 0, "/", "uwbd")
    assert node in live["tokens"]
    pubs = [t for t in live["tokens"] if t != node]
    assert len(pubs) == len(TYPES)
    for token in pubs:
        parts = token.split("/")
        assert len(parts) == 13 and parts[:5] == ["@ros2_lv", "0", zid, "0", parts[4]]
        topic = parts[9].replace("%", "/")
        msgtype = TYPES[topic]
        qos = rz.Qos(durability=rz.TRANSIENT_LOCAL, depth=1) if topic == "/tf_static" else \
            rz.Qos(depth=10)
        assert token == rz.publisher_token(0, zid, 0, int(parts[4]), "/", "uwbd", topic,
                                           rz.dds_type_name(msgtype), JAZZY.hash_rihs01(msgtype),
                                           qos)
    assert sorted(int(t.split("/")[4]) for t in pubs) == list(range(1, len(TYPES) + 1))
    assert live["after"] == []  # a stopped daemon leaves the graph


def test_a_late_subscriber_gets_the_static_transforms(live: dict[str, Any]) -> None:
    """/tf_static is transient local: a subscriber that joins later still gets it, from the
    publisher's cache, as a ROS 2 transient-local subscription would."""
    (payload,) = live["late_tf_static"]
    msg = JAZZY.deserialize_cdr(payload, TYPES["/tf_static"])
    assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [
        ("base_link", "base_link_imu"), ("base_link", "base_link_uwb")]


def test_diagnostics_say_the_filters_health(live: dict[str, Any]) -> None:
    _, samples = _by_topic(live["seen"])["/diagnostics"]
    last = JAZZY.deserialize_cdr(samples[-1][0], TYPES["/diagnostics"])
    (status,) = last.status
    assert status.name == "uwbd: filter" and status.hardware_id
    values = {kv.key: kv.value for kv in status.values}
    # (the emulated layout's levels may be over the default alert limits: that alone)
    assert values["phase"] in {"tracking", "aligning", "coasting", "recovering"} or (
        values["phase"] == "degraded" and values["faults"] == "position_uncertain")
    assert int(status.level) == (0 if status.message == "tracking" else status.level)


def test_the_status_and_the_start_line_say_what_is_published(live: dict[str, Any]) -> None:
    ros2 = live["status"]["ros2"]
    assert ros2["state"] == "up" and ros2["node"] == "/uwbd" and ros2["domain_id"] == 0
    assert set(ros2["published"]) == set(TYPES) and ros2["published"]["/uwbd/pose"] > 0
    assert "ROS 2 over rmw_zenoh (jazzy): domain 0 (default), node /uwbd" in live["stderr"]


def test_echo_ros2_decodes_what_the_daemon_publishes(live: dict[str, Any]) -> None:
    echo = live["echo"]
    assert echo.returncode == 0, echo.stderr
    lines = echo.stdout.splitlines()
    assert len(lines) == 3 and all(x.startswith("/uwbd/pose #") and " p=(" in x for x in lines)
    seqs = [int(x.split()[1][1:]) for x in lines]
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
    static = live["echo_static"]
    assert static.returncode == 0, static.stderr
    assert static.stdout.startswith("/tf_static #1 ") and "base_link→base_link_imu" in static.stdout


# -- the packed CDR, against rosbags ---------------------------------------------------------

FLOATS = st.floats(allow_nan=True, allow_infinity=True)
FRAME = st.from_regex(r"[a-z_][a-z0-9_/]{0,12}", fullmatch=True)


@settings(max_examples=150, deadline=None)
@given(nav=FRAME, body=FRAME, t_ns=st.integers(0, 2**31 * 1_000_000_000 - 1),  # ROS's int32 seconds
       position=st.tuples(*[FLOATS] * 3), velocity=st.tuples(*[FLOATS] * 3),
       quat=st.tuples(*[st.floats(-1, 1)] * 4), cov=st.lists(FLOATS, min_size=36, max_size=36),
       gyro=st.tuples(*[FLOATS] * 3), acc=st.tuples(*[FLOATS] * 3),
       variances=st.tuples(st.floats(0, 1), st.floats(0, 1)))
def test_packed_messages_are_rosbags_bytes(nav: str, body: str, t_ns: int, position: Any,
                                           velocity: Any, quat: Any, cov: list[float],
                                           gyro: Any, acc: Any, variances: Any) -> None:
    """What the live topics send is what rosbags serialises, byte for byte, for any numbers
    and frame names (their lengths move the padding)."""
    frames = FrameIds(nav, body)
    pose = Pose(t_ns, position, velocity, quat, tuple(cov), "", True)
    with np.errstate(all="ignore"):  # infinite velocities make NaN body velocities: as rosbags
        for role, (layout, values) in pose_layouts(frames).items():
            msg = {"pose": pose_msg, "odom": odometry_msg, "tf": tf_msg}[role](pose, frames)
            assert layout.pack(t_ns, values(pose)) == bytes(
                TYPESTORE.serialize_cdr(msg, msg.__msgtype__)), role
    sample = ImuSample(t_ns, acc, gyro)
    assert imu_layout(frames).pack(t_ns, imu_values(sample, *variances)) == bytes(
        TYPESTORE.serialize_cdr(imu_msg(sample, frames, *variances), "sensor_msgs/msg/Imu"))
