"""The commands on logs and captures: ``replay``, ``recover``, ``export``, ``dump``."""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

from drivers import PARSERS, Frame
from uwbd.codec import frame_to_dict
from uwbd.commands.common import (
    RunError,
    UsageError,
    driver_name,
    log_config,
    open_log,
    require_matching_sources,
    require_replayable,
    writable_folder,
    written,
)
from uwbd.config import ConfigError, parse
from uwbd.logs.reading import LogContents, not_a_log, recover
from uwbd.service.replay import replay

READ_CHUNK_BYTES = 65536


def cmd_dump(args: argparse.Namespace) -> int:
    """Decode a byte capture: one JSON object per frame on stdout, parser counters on stderr.

    A capture has no receive times, so every frame's ``t_ns`` is 0.
    """
    parser = PARSERS[driver_name(args.driver)]()
    try:
        stream: BinaryIO = sys.stdin.buffer if args.file == "-" else open(args.file, "rb")  # noqa: SIM115
    except OSError as err:
        raise UsageError(f"cannot read {args.file}: {err.strerror}") from err
    with stream:
        while chunk := stream.read(READ_CHUNK_BYTES):
            _print_frames(parser.feed(chunk, 0))
        _print_frames(parser.flush())
    print(json.dumps({"parser_stats": parser.stats.as_dict()}), file=sys.stderr)
    return 0


def _print_frames(frames: Sequence[Frame]) -> None:
    for frame in frames:
        sys.stdout.write(json.dumps(frame_to_dict(frame)) + "\n")


def cmd_replay(args: argparse.Namespace) -> int:
    """A log's reads through the live pipeline; the poses to -o, a summary to stdout."""
    path, contents = open_log(args.log, "replaying")
    config_toml = log_config(args, path, contents)
    require_replayable(path, contents)
    if args.config and config_toml is not None:
        try:
            config = parse(config_toml, args.config)
        except ConfigError as err:
            raise UsageError(str(err)) from err
        require_matching_sources(path, contents, config, args.config)
    out = Path(args.output) if args.output else None
    if out is not None:
        writable_folder(out, "the replayed log")
        if out.exists() and out.resolve() == path.resolve():
            raise UsageError(f"{out}: give another file to write, not the log itself")
    # the log and everything imported live to the end: the cyclic garbage collector need
    # not walk them again and again (measured: 11 % of a 10-minute replay, and pauses of
    # up to 90 ms, without this)
    gc.freeze()
    with contextlib.ExitStack() as stack:  # the log to a new file, renamed over -o when whole
        tmp = None if out is None else stack.enter_context(written(out, "the replayed log"))
        try:
            pipeline, poses = replay(contents, str(path), tmp, args.realtime,
                                     progress=sys.stderr.isatty(), config_toml=config_toml)
        except ConfigError as err:
            raise UsageError(str(err)) from err
        log_errors = [str(getattr(sink, "error", "")) for sink in pipeline.sinks
                      if getattr(sink, "error", "")]
        print(f"{path}: {pipeline.poses} poses; filter {pipeline.filter.status}")
        if poses.poses:
            x, y, z = poses.poses[-1].position_m
            print(f"last pose ({x:.3f}, {y:.3f}, {z:.3f}) m")
        for line in _findings(pipeline.filter.diagnostics()):
            print(line)
        if pipeline.poses == 0:
            raise RunError(f"{path}: no pose came out of the replay (the filter: "
                           f"{pipeline.filter.status}){_why_no_pose(contents)}"
                           + ("; nothing written" if out is not None else ""))
        if tmp is not None and (log_errors or not tmp.is_file()):
            raise RunError(f"{out}: not written: the replayed log could not be written whole: "
                           f"{log_errors[0] if log_errors else 'the file was not written'}")
    if out is not None:
        print(f"written to {out}")
    return 0


def _why_no_pose(contents: LogContents) -> str:
    """What in a log keeps a filter from starting, where the log itself shows it."""
    times = {m.log_time_ns for m in contents.messages if m.topic.startswith("/raw/")}
    if len(times) == 1:
        return (f": every read has the log time {times.pop()} ns, and the filter runs on the "
                "reads' receive times")
    return ""


def _findings(diagnostics: dict[str, Any]) -> list[str]:
    """What the filter found of the installation by the end of a replay, a line each."""
    lines = [str(f["finding"]) for f in diagnostics.get("anchor_findings", [])]
    if "anchor_suspected" in diagnostics:
        lines.append(str(diagnostics["anchor_suspected"]["finding"]))
    if diagnostics.get("mounting_finding"):
        lines.append(str(diagnostics["mounting_finding"]))
    if "lever_arm_finding" in diagnostics:
        lines.append(str(diagnostics["lever_arm_finding"]["finding"]))
    if "lever_arm_estimate_m" in diagnostics:
        x, y, z = diagnostics["lever_arm_estimate_m"]
        lines.append(f"lever arm by the data: ({x:+.3f}, {y:+.3f}, {z:+.3f}) m "
                     "(IMU -> antenna, body axes; compare imu.lever_arm_m)")
    return lines


def cmd_recover(args: argparse.Namespace) -> int:
    """Rewrite a log cut short by a crash (no footer) as a valid MCAP file."""
    source, target = Path(args.log), Path(args.output)
    if not source.exists():
        raise UsageError(f"cannot read {source}: no such file")
    problem = not_a_log(source)
    if problem:
        raise UsageError(problem)
    if target.exists() and target.resolve() == source.resolve():
        raise UsageError(f"{target}: give another file to write, not the log itself")
    with written(target, "the recovered log") as tmp:
        result = recover(source, tmp)
        if result.messages == 0:  # an empty log claims a recovery that did not happen
            raise RunError(f"{source}: no message could be recovered, nothing written"
                           + (f" ({result.error})" if result.error else ""))
    print(f"{target}: {result.messages} messages recovered from {source}"
          + (f" ({result.error})" if result.truncated else
             " (it was complete)"))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """A log as a ROS 2 bag folder (metadata.yaml + MCAP, CDR): see :mod:`uwbd.tools.ros2_bag`."""
    path, contents = open_log(args.log, "exporting")
    out = Path(args.ros2)
    if out.exists() or out.is_symlink():
        raise UsageError(f"cannot write the bag {out}: it exists (a bag is a new folder: "
                         "remove it or give another name)")
    writable_folder(out, "the bag")
    config_toml = log_config(args, path, contents)
    if config_toml is not None or not any(m.topic == "/pose" for m in contents.messages):
        require_replayable(path, contents)  # the poses come from a replay
    try:
        from uwbd.tools.ros2_bag import export_ros2
    except ImportError as err:
        raise UsageError(f"export needs the tools extra ({err.name} is missing): pip install "
                         "'uwbd[tools]' (from a checkout: pip install '.[tools]')") from err
    try:
        result = export_ros2(contents, str(path), out, config_toml,
                             progress=sys.stderr.isatty())
    except ConfigError as err:
        raise UsageError(str(err)) from err
    except OSError as err:
        raise RunError(f"cannot write the bag {out}: {err.strerror or err}") from err
    n = {role: result.counts.get(topic, 0) for role, topic in result.topics.items()}
    origin = "the log's own" if result.poses_from == "log" else "replayed"
    print(f"{out}: ROS 2 bag (MCAP) from {path}: {n.get('pose', 0)} poses ({origin}), "
          f"{n.get('imu', 0)} IMU samples, {n.get('truth', 0)} truth poses; "
          f"topics {', '.join(sorted(result.counts))}")
    return 0
