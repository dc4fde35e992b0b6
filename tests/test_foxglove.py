"""Logs and a live daemon as Foxglove sees them: every channel has a schema Foxglove reads,
every record fits its channel's schema and Foxglove's own definitions, raw reads open as
protobuf and still replay bit for bit (old logs too), and ``--foxglove`` serves the same
channels over the Foxglove WebSocket protocol. Real files, subprocesses and sockets."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import struct
import subprocess
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
from mcap.reader import make_reader
from mcap.writer import Writer
from procs import UNBUFFERED, UWBD, one_line, read_until, uwbd

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.codec import frame_from_dict
from uwbd.config import parse
from uwbd.logs import foxglove as fx
from uwbd.logs.mcaplog import METADATA_NAME
from uwbd.logs.reading import read_log
from uwbd.logs.sink import McapSink
from uwbd.service.pipeline import Pipeline
from uwbd.service.replay import replay
from uwbd.tools.logtools import simulation_toml, write_simulation
from uwbd.tools.simulator import DEFAULT_SEGMENTS, SimConfig, simulate

VIEWER = ("/tf", "/anchors", "/trajectory")


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated run (raw device bytes + truth), as tests/test_operability.py's."""
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    write_simulation(simulate(SimConfig(seed=5, segments=DEFAULT_SEGMENTS[:4])), path)
    return path


@pytest.fixture(scope="module")
def replayed(sim_log: Path) -> Path:
    """``uwbd replay -o`` of the simulated log: what the daemon writes, through the CLI."""
    out = sim_log.with_name("replayed.mcap")
    result = uwbd("replay", str(sim_log), "-o", str(out))
    assert result.returncode == 0, result.stderr
    return out


def channels_of(path: Path) -> dict[str, tuple[str, str, str, bytes]]:
    """topic -> (message encoding, schema name, schema encoding, schema data), as a seeking
    reader (Foxglove's kind) sees the file's summary."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = {}
    for ch in summary.channels.values():
        schema = summary.schemas.get(ch.schema_id)
        out[ch.topic] = (ch.message_encoding, schema.name if schema else "",
                         schema.encoding if schema else "", schema.data if schema else b"")
    return out


def messages_by_topic(path: Path) -> dict[str, list[bytes]]:
    """Each topic's messages as stored (not decoded by uwbd)."""
    out: dict[str, list[bytes]] = defaultdict(list)
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            out[channel.topic].append(message.data)
    return out


def foxglove_accepts(schema: dict[str, Any], where: str = "") -> None:
    """Fail where Foxglove's JSON Schema reader (``parseJsonSchema`` in Foxglove's
    mcap-support) would throw: each object needs ``properties``; each property one ``type``
    of object, array, string, number, integer, boolean, or a ``oneOf`` of numeric consts;
    array items one of those but array; ``contentEncoding`` only base64 on a string."""
    assert schema.get("type") == "object", f"{where}: not an object"
    assert isinstance(schema.get("properties"), dict), f"{where}: no properties"
    for name, prop in schema["properties"].items():
        at = f"{where}.{name}"
        if "oneOf" in prop:
            assert all(isinstance(alt.get("const"), int) for alt in prop["oneOf"]), at
            continue
        kind = prop.get("type")
        assert kind in ("object", "array", "string", "number", "integer", "boolean"), (at, kind)
        if kind == "object":
            foxglove_accepts(prop, at)
        elif kind == "array":
            items = prop["items"]
            assert items.get("type") in ("object", "string", "number", "integer",
                                         "boolean"), (at, items)
            assert "contentEncoding" not in items, at
            if items["type"] == "object":
                foxglove_accepts(items, at + "[]")
        elif kind == "string":
            assert prop.get("contentEncoding") in (None, "base64"), at


# -- the log ---------------------------------------------------------------------------------

def test_every_json_channel_has_a_schema_foxglove_reads_and_every_record_fits(
        replayed: Path) -> None:
    channels = channels_of(replayed)
    expected = {"/pose": "foxglove.PoseInFrame", "/tf": "foxglove.FrameTransform",
                "/anchors": "foxglove.SceneUpdate", "/trajectory": "foxglove.PosesInFrame",
                "/imu": "uwbd.ImuSample", "/uwb": "uwbd.UwbRanges", "/status": "uwbd.Status",
                "/raw/imu": "uwbd.Raw", "/raw/uwb": "uwbd.Raw",
                # the source's truth, which replay carries over
                "/truth": "foxglove.PoseInFrame", "/truth/trajectory": "foxglove.PosesInFrame"}
    assert {t: c[1] for t, c in channels.items()} == expected
    messages = messages_by_topic(replayed)
    checked = 0
    for topic, (encoding, name, schema_encoding, data) in channels.items():
        if encoding != "json":
            continue
        assert schema_encoding == "jsonschema", topic
        schema = json.loads(data)
        assert schema["title"] == name
        jsonschema.Draft202012Validator.check_schema(schema)
        foxglove_accepts(schema, topic)
        validator = jsonschema.Draft202012Validator(schema)
        for raw in messages[topic]:
            record = json.loads(raw)
            errors = sorted(validator.iter_errors(record), key=str)
            assert not errors, (topic, errors[0].message, list(errors[0].absolute_path))
            # the exact time in JavaScript and the integer one agree
            t = record.get("timestamp")
            if "t_ns" in record:
                assert t["sec"] * 10**9 + t["nsec"] == record["t_ns"], topic
            checked += 1
    assert len(messages["/pose"]) > 500 and len(messages["/pose"]) == len(messages["/tf"])
    assert checked > 5_000


def test_the_viewer_channels_say_what_the_3d_panel_needs(replayed: Path) -> None:
    contents = read_log(replayed)
    config = parse(contents.metadata["config_toml"], "log")
    poses = list(contents.json("/pose"))
    transforms = list(contents.json("/tf"))
    for pose, tf in zip(poses, transforms, strict=True):
        assert pose["frame_id"] == tf["parent_frame_id"] == "enu"
        assert tf["child_frame_id"] == "base_link" and tf["timestamp"] == pose["timestamp"]
        assert tf["translation"] == pose["pose"]["position"]
        assert tf["rotation"] == pose["pose"]["orientation"]
    (scene,) = contents.json("/anchors")  # one anchor set, written as the file starts
    first = min(m.log_time_ns for m in contents.messages)
    assert next(m for m in contents.messages if m.topic == "/anchors").log_time_ns == first
    spheres = {e["id"]: e["spheres"][0]["pose"]["position"] for e in scene["entities"]}
    assert spheres == {f"anchor-{a}": {"x": x, "y": y, "z": z}
                       for a, (x, y, z) in config.anchors_m.items()}
    assert [e["texts"][0]["text"] for e in scene["entities"]] == [
        f"anchor {a}" for a in sorted(config.anchors_m)]
    trails = [(m.log_time_ns, json.loads(m.data)) for m in contents.messages
              if m.topic == "/trajectory"]
    duration_s = (poses[-1]["t_ns"] - poses[0]["t_ns"]) / 1e9
    assert abs(len(trails) - duration_s) <= 2  # about once a second
    last = trails[-1][1]
    assert last["frame_id"] == "enu" and len(last["poses"]) >= 2 * duration_s - 3
    # its points are poses (to 0.1 mm), the last one recent
    end = last["poses"][-1]["position"]
    near = [p for p in poses if all(abs(p["pose"]["position"][k] - end[k]) < 1e-3
                                    for k in "xyz")]
    assert near and near[-1]["t_ns"] >= poses[-1]["t_ns"] - 1_500_000_000


def test_frame_names_come_from_the_config(sim_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "named.mcap"
    result = uwbd("replay", str(sim_log), "-o", str(out), "--set", "robot.nav_frame_id=world",
                  "--set", "robot.body_frame_id=rover")
    assert result.returncode == 0, result.stderr
    contents = read_log(out)
    assert {p["frame_id"] for p in contents.json("/pose")} == {"world"}
    assert {(t["parent_frame_id"], t["child_frame_id"]) for t in contents.json("/tf")} == {
        ("world", "rover")}
    assert {e["frame_id"] for s in contents.json("/anchors") for e in s["entities"]} == {
        "world"}
    assert {t["frame_id"] for t in contents.json("/trajectory")} == {"world"}


def test_simulated_log_keeps_the_truth_schema_and_has_a_truth_trajectory(sim_log: Path) -> None:
    channels = channels_of(sim_log)
    assert channels["/truth"][:3] == ("json", "foxglove.PoseInFrame", "jsonschema")
    assert channels["/truth/trajectory"][1] == "foxglove.PosesInFrame"
    assert channels["/anchors"][1] == "foxglove.SceneUpdate"  # from the log's config
    messages = messages_by_topic(sim_log)
    for topic in ("/truth", "/truth/trajectory", "/anchors"):
        validator = jsonschema.Draft202012Validator(json.loads(channels[topic][3]))
        for raw in messages[topic]:
            validator.validate(json.loads(raw))


def test_raw_reads_are_protobuf_and_replay_bit_for_bit(sim_log: Path, replayed: Path) -> None:
    channels = channels_of(replayed)
    encoding, name, schema_encoding, data = channels["/raw/imu"]
    assert (encoding, name, schema_encoding) == ("protobuf", "uwbd.Raw", "protobuf")
    files = descriptor_pb2.FileDescriptorSet.FromString(data)
    (proto,) = files.file
    assert (proto.package, proto.syntax, [m.name for m in proto.message_type]) == (
        "uwbd", "proto3", ["Raw"])
    (field,) = proto.message_type[0].field
    assert (field.name, field.number, field.type) == (
        "data", 1, descriptor_pb2.FieldDescriptorProto.TYPE_BYTES)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    raw_class = message_factory.GetMessageClass(pool.FindMessageTypeByName("uwbd.Raw"))
    decoded = [m for m in read_log(replayed).messages if m.topic.startswith("/raw/")]
    stored = messages_by_topic(replayed)
    by_protobuf = {t: [raw_class.FromString(d).data for d in stored[t]]
                   for t in ("/raw/imu", "/raw/uwb")}
    assert [m.data for m in decoded if m.topic == "/raw/imu"] == by_protobuf["/raw/imu"]
    assert [m.data for m in decoded if m.topic == "/raw/uwb"] == by_protobuf["/raw/uwb"]
    # the bytes read are the simulated log's, and replaying either gives the same poses
    original = [(m.topic, m.log_time_ns, m.data) for m in read_log(sim_log).messages
                if m.topic.startswith("/raw/")]
    assert [(m.topic, m.log_time_ns, m.data) for m in decoded] == original
    logged = [(p["t_ns"], p["pose"]) for p in read_log(replayed).json("/pose")]
    again = replay(read_log(replayed), str(replayed))[1].poses
    assert [(p.t_ns, {"position": dict(zip("xyz", p.position_m, strict=True)),
                      "orientation": dict(zip("xyzw", p.orientation_xyzw, strict=True))})
            for p in again] == logged
    # any valid encoding of uwbd.Raw reads back (what another writer may produce)
    for chunk in (b"", b"\x55" * 300, bytes(range(256))):
        assert fx.decode_raw(raw_class(data=chunk).SerializeToString()) == chunk
        assert raw_class.FromString(fx.encode_raw(chunk)).data == chunk


def test_an_old_log_with_schemaless_raw_reads_still_replays(sim_log: Path,
                                                             tmp_path: Path) -> None:
    """A log as uwbd wrote it before: /raw/* schemaless, encoding uwbd.raw."""
    new = read_log(sim_log)
    old = tmp_path / "old.mcap"
    with old.open("wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata(METADATA_NAME, new.metadata)
        channels: dict[str, int] = {}
        for m in new.messages:
            if m.topic.startswith("/raw/"):
                if m.topic not in channels:
                    channels[m.topic] = w.register_channel(m.topic, "uwbd.raw", 0)
                w.add_message(channels[m.topic], m.log_time_ns, m.data, m.log_time_ns)
        w.finish()
    assert {c[0] for c in channels_of(old).values()} == {"uwbd.raw"}
    as_old = replay(read_log(old), str(old))[1].poses
    as_new = replay(new, str(sim_log))[1].poses
    assert as_old == as_new and len(as_old) > 500
    result = uwbd("replay", str(old), "-o", str(tmp_path / "o.mcap"))
    assert result.returncode == 0, result.stderr


def test_every_rotated_file_shows_the_anchors(sim_log: Path, tmp_path: Path) -> None:
    contents = read_log(sim_log)
    config = parse(contents.metadata["config_toml"], "log")
    sink = McapSink(config, directory=tmp_path / "logs", rotate_ns=5_000_000_000)
    pipeline = Pipeline(config, [sink])
    for m in contents.messages:
        if m.topic.startswith("/raw/"):
            pipeline.on_bytes(m.topic[5:], m.log_time_ns, m.data)
    pipeline.finish()
    pipeline.close()
    assert len(sink.files) >= 3
    trails = []
    for path in sink.files:
        file = read_log(path)
        assert file.messages[0].topic == "/anchors", path  # the first record of each file
        trails += list(file.json("/trajectory"))
    # the trajectory goes on across files: it grows up to its window, never restarts
    sizes = [len(t["poses"]) for t in trails]
    assert sizes == sorted(sizes) and sizes[-1] >= 2 * 5 * (len(sink.files) - 1)


def test_device_reported_anchors_update_the_scene(tmp_path: Path) -> None:
    """A DWM1001 sends anchor positions with its ranges: the scene follows them."""
    config = parse("", "no anchors configured")
    sink = McapSink(config, path=tmp_path / "a.mcap")
    epoch = UwbRanges(10**18, (AnchorRange(7, 3.0, 90.0, (1.0, 2.0, 2.5)),))
    sink.frame(epoch)
    sink.frame(UwbRanges(10**18 + 10**8, (AnchorRange(7, 3.1, 90.0, (1.0, 2.0, 2.5)),
                                          AnchorRange(9, 4.0, 80.0, (5.0, 2.0, 2.5)))))
    sink.frame(UwbRanges(10**18 + 2 * 10**8, (AnchorRange(9, 4.1, 80.0, (5.0, 2.0, 2.5)),)))
    sink.close()
    scenes = list(read_log(tmp_path / "a.mcap").json("/anchors"))
    assert [[e["id"] for e in s["entities"]] for s in scenes] == [
        ["anchor-7"], ["anchor-7", "anchor-9"]]
    # and the /uwb records leave out what the device did not send, fitting their schema
    uwb = list(read_log(tmp_path / "a.mcap").json("/uwb"))
    validator = jsonschema.Draft202012Validator(fx.UWB_SCHEMA)
    for record in uwb:
        validator.validate(record)
    assert frame_from_dict(uwb[0]) == epoch


def test_frame_schemas_follow_the_dataclasses() -> None:
    for cls, schema in ((ImuSample, fx.IMU_SCHEMA), (UwbRanges, fx.UWB_SCHEMA)):
        fields = set(cls.__dataclass_fields__)
        assert set(schema["properties"]) == fields | {"type", "timestamp"}
        assert schema["additionalProperties"] is False
    ranges = fx.UWB_SCHEMA["properties"]["ranges"]["items"]
    assert set(ranges["properties"]) == set(AnchorRange.__dataclass_fields__)
    assert fx.IMU_SCHEMA["properties"]["acc_mps2"]["items"] == {"type": "number"}
    assert "m/s²" in fx.IMU_SCHEMA["properties"]["acc_mps2"]["description"]
    assert "JavaScript" in fx.IMU_SCHEMA["properties"]["t_ns"]["description"]
    for schema in (fx.POSE_SCHEMA, fx.TRUTH_SCHEMA, *fx.SCHEMAS.values(), fx.IMU_SCHEMA,
                   fx.UWB_SCHEMA):
        foxglove_accepts(schema, schema["title"])


def test_foxglove_types_match_foxglove_s_own_definitions(replayed: Path, sim_log: Path) -> None:
    """Foxglove's definitions as its SDK ships them (protobuf descriptors): every field our
    schemas declare is one of theirs with the same kind, and every logged record of those
    channels converts into Foxglove's message, unknown fields refused (uwbd's extra /pose
    fields aside)."""
    messages = pytest.importorskip("foxglove.messages")  # the foxglove extra

    def proto_class(name: str) -> Any:
        pool = descriptor_pool.DescriptorPool()
        files = descriptor_pb2.FileDescriptorSet.FromString(
            getattr(messages, name).get_schema().data)
        for file in files.file:
            pool.Add(file)
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"foxglove.{name}"))

    kinds = {"TYPE_DOUBLE": "number", "TYPE_FLOAT": "number", "TYPE_STRING": "string",
             "TYPE_BOOL": "boolean", "TYPE_FIXED32": "integer", "TYPE_INT32": "integer",
             "TYPE_ENUM": "enum", "TYPE_MESSAGE": "object", "TYPE_BYTES": "string"}

    def repeated(field: Any) -> bool:
        return bool(getattr(field, "is_repeated", None) or getattr(field, "label", 0) == 3)

    def check(schema: dict[str, Any], descriptor: Any, at: str) -> None:
        for prop, declared in schema["properties"].items():
            sub = declared
            field = descriptor.fields_by_name.get(prop)
            assert field is not None, f"{at}.{prop}: not in Foxglove's {descriptor.full_name}"
            kind = kinds[descriptor_pb2.FieldDescriptorProto.Type.Name(field.type)]
            if repeated(field):
                assert sub["type"] == "array", f"{at}.{prop}"
                sub = sub["items"]
            if kind == "enum":
                assert "oneOf" in sub, f"{at}.{prop}"
            elif field.message_type is not None and field.message_type.full_name in (
                    "google.protobuf.Timestamp", "google.protobuf.Duration"):
                assert set(sub["properties"]) == {"sec", "nsec"}, f"{at}.{prop}"
            else:
                assert sub["type"] == kind, f"{at}.{prop}: {sub['type']} vs {kind}"
                if kind == "object":
                    check(sub, field.message_type, f"{at}.{prop}")

    def to_proto_json(value: Any, descriptor: Any) -> Any:
        """Foxglove's JSON time {sec, nsec} as protobuf's JSON (RFC 3339, "1.5s")."""
        if descriptor.full_name in ("google.protobuf.Timestamp", "google.protobuf.Duration"):
            sec, nsec = value["sec"], value["nsec"]
            if descriptor.full_name.endswith("Duration"):
                return f"{sec}.{nsec:09d}s"
            return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(sec)) + f".{nsec:09d}Z"
        out = {}
        for key, sub in value.items():
            field = descriptor.fields_by_name[key]
            if field.message_type is None:
                out[key] = sub
            elif repeated(field):
                out[key] = [to_proto_json(v, field.message_type) for v in sub]
            else:
                out[key] = to_proto_json(sub, field.message_type)
        return out

    pose_extras = set(fx.POSE_SCHEMA["properties"]) - set(fx.TRUTH_SCHEMA["properties"])
    channels = {**channels_of(sim_log), **channels_of(replayed)}
    stored = {**messages_by_topic(sim_log), **messages_by_topic(replayed)}
    for topic in ("/pose", "/truth", "/tf", "/anchors", "/trajectory", "/truth/trajectory"):
        name = channels[topic][1].removeprefix("foxglove.")
        cls = proto_class(name)
        schema = json.loads(channels[topic][3])
        ours = dict(schema, properties={k: v for k, v in schema["properties"].items()
                                        if k not in pose_extras and k != "t_ns"})
        check(ours, cls.DESCRIPTOR, topic)
        for raw in stored[topic][:200]:
            record = {k: v for k, v in json.loads(raw).items()
                      if k not in pose_extras and k != "t_ns"}
            json_format.ParseDict(to_proto_json(record, cls.DESCRIPTOR), cls())


# -- live ------------------------------------------------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_demo_serves_the_channels_live_over_the_foxglove_websocket(tmp_path: Path) -> None:
    pytest.importorskip("foxglove")
    websockets = pytest.importorskip("websockets")
    port = free_port()
    demo = subprocess.Popen([*UWBD, "demo", "--foxglove", f"127.0.0.1:{port}", "--duration",
                             "20"], cwd=tmp_path, env=UNBUFFERED, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        said = read_until(demo, b"Foxglove live view at", 20, "stderr")
        assert f"ws://127.0.0.1:{port}".encode() in said
        got = asyncio.run(_watch(websockets, port, seconds=4.0))
        demo.send_signal(signal.SIGINT)
        out, err = demo.communicate(timeout=30)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.communicate()
    assert demo.returncode == 0, err.decode()
    assert b"Traceback" not in err and b"summary:" in out
    info, adverts, frames = got
    assert info["op"] == "serverInfo" and "uwbd" in info["name"]
    topics = {c["topic"]: c for c in adverts}
    assert {"/pose", "/tf", "/anchors", "/trajectory", "/status", "/imu", "/uwb",
            "/raw/imu", "/raw/uwb"} <= set(topics)
    assert topics["/pose"]["schemaName"] == "foxglove.PoseInFrame"
    assert topics["/pose"]["encoding"] == "json" and topics["/raw/imu"]["encoding"] == "protobuf"
    pose_schema = json.loads(topics["/pose"]["schema"])
    foxglove_accepts(pose_schema, "/pose")
    poses, transforms = frames["/pose"], frames["/tf"]
    assert len(poses) > 50 and len(transforms) > 50  # 4 s at 50 Hz, give or take
    times = [t for t, _ in poses]
    assert times == sorted(times) and len(set(times)) == len(times)
    validator = jsonschema.Draft202012Validator(pose_schema)
    for t, pose in poses:
        validator.validate(pose)
        assert pose["frame_id"] == "enu" and pose["t_ns"] == t
        assert pose["timestamp"]["sec"] * 10**9 + pose["timestamp"]["nsec"] == t
    assert {(m["parent_frame_id"], m["child_frame_id"]) for _, m in transforms} == {
        ("enu", "base_link")}
    # the server went away with the demo
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", port), timeout=2):
        pass


async def _watch(websockets: Any, port: int, seconds: float) -> tuple[
        dict[str, Any], list[dict[str, Any]], dict[str, list[tuple[int, Any]]]]:
    """Connect as Foxglove does, subscribe to /pose and /tf, decode ``messageData`` frames
    (opcode 0x01, u32 subscription id, u64 log time, payload) for ``seconds``."""
    async with websockets.connect(f"ws://127.0.0.1:{port}",
                                  subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                  open_timeout=10, max_size=None) as ws:
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        adverts: list[dict[str, Any]] = []
        while not {"/pose", "/tf"} <= {c["topic"] for c in adverts}:
            message = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if message.get("op") == "advertise":
                adverts += message["channels"]
        ids = {c["topic"]: c["id"] for c in adverts}
        subscriptions = {1: "/pose", 2: "/tf"}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sub, "channelId": ids[topic]} for sub, topic in subscriptions.items()]}))
        frames: dict[str, list[tuple[int, Any]]] = defaultdict(list)
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                message = await asyncio.wait_for(ws.recv(), left)
            except asyncio.TimeoutError:
                break
            if isinstance(message, bytes) and message[0] == 0x01:
                sub, log_time = struct.unpack_from("<IQ", message, 1)
                frames[subscriptions[sub]].append((log_time, json.loads(message[13:])))
            elif isinstance(message, str) and json.loads(message).get("op") == "advertise":
                adverts += json.loads(message)["channels"]
        return info, adverts, frames


BLOCK_FOXGLOVE = '''
import importlib.abc, sys

class NotInstalled(importlib.abc.MetaPathFinder):
    """As on a robot installed without the foxglove extra."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "foxglove":
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NotInstalled())
'''


def test_foxglove_option_problems_are_one_line_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "sitecustomize.py").write_text(BLOCK_FOXGLOVE)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    one_line(uwbd("demo", "--foxglove", "--duration", "1", env=env, cwd=tmp_path), 2,
             "--foxglove needs the foxglove extra", "pip install 'uwbd[foxglove]'")
    # the daemon without the extra: the same line, before any port is opened
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(simulation_toml(simulate(SimConfig(seed=1, segments=((1.0, 0, 0, 0),)))))
    one_line(uwbd("run", "-c", str(cfg), "--foxglove", env=env, cwd=tmp_path), 2,
             "--foxglove needs the foxglove extra")
    pytest.importorskip("foxglove")
    one_line(uwbd("demo", "--foxglove", "localhost:http", cwd=tmp_path), 2,
             "--foxglove", "expected HOST:PORT")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = uwbd("demo", "--foxglove", f"127.0.0.1:{port}", "--duration", "1",
                      cwd=tmp_path)
    one_line(result, 2, f"--foxglove 127.0.0.1:{port}: cannot serve there")
    assert not result.stdout  # nothing started
