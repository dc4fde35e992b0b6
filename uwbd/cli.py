"""The ``uwbd`` command line: one entry point, one subcommand per job.

Everything a command says goes through :mod:`uwbd.journal` (``-v``/``-q`` on every command).
Errors the user can fix (a missing or malformed file, an unknown driver, a bad option value,
a folder that cannot be written) print one line ``uwbd <command>: <what and where>`` and
exit 2; a run that fails while working (the pipeline raised, an output could not be
written) exits 1; an interrupted run exits 0 after cleaning up. No traceback reaches the
user (``-v`` shows one for an internal error); output piped into ``head`` ends quietly.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import zenoh

from drivers import PARSERS, Frame
from drivers.emulator import ENCODERS, DeviceSpec, Emulator, Faults, Window
from drivers.emulator.scenario import CircleScenario
from uwbd import __version__, journal
from uwbd.codec import frame_to_dict
from uwbd.config import Config, ConfigError, apply_overrides, default_robot_name
from uwbd.config import load as load_config
from uwbd.fusion import native
from uwbd.logs.mcaplog import LogContents, not_a_log, read_log, recover
from uwbd.logs.replay import replay
from uwbd.service.daemon import PipelineError
from uwbd.service.daemon import run as run_daemon
from uwbd.service.demo import run_demo
from uwbd.service.echo import EchoError, dial_endpoints, echo
from uwbd.service.interrupt import quiet_stdout, shielded, wait_until
from uwbd.service.router import DEFAULT_LISTEN, RouterError, run_router
from uwbd.service.zenohsink import zenoh_reason
from uwbd.tools.importer import (
    INROL_LEVER_ARM_M,
    INROL_MOUNTING,
    Dataset,
    DatasetError,
    load_iasl,
    load_inrol,
)
from uwbd.tools.logtools import load_recording, write_dataset, write_simulation
from uwbd.tools.simulator import Z_DOWN, SimConfig, segments_for, simulate

READ_CHUNK_BYTES = 65536
LOG = journal.get("cli")


class UsageError(Exception):
    """A problem with what the user asked for; printed as one line, exit code 2."""


class RunError(Exception):
    """The command failed while working (an output it could not write); exit code 1."""


def _writable_folder(target: Path, what: str) -> None:
    """Fail before any work when ``target`` (a file to write) cannot be created."""
    folder = target.parent
    if not folder.is_dir():
        raise UsageError(f"cannot write {what} {target}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"cannot write {what} {target}: folder {folder} is not writable")
    if target.is_dir():
        raise UsageError(f"cannot write {what} {target}: it is a folder")


def _driver(name: str) -> str:
    if name not in PARSERS:
        raise UsageError(f"unknown driver {name!r} (known: {', '.join(PARSERS)})")
    return name


def cmd_dump(args: argparse.Namespace) -> int:
    """Decode a byte capture: one JSON object per frame on stdout, parser counters on stderr.

    A capture has no receive times, so every frame's ``t_ns`` is 0.
    """
    parser = PARSERS[_driver(args.driver)]()
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


def _faults(args: argparse.Namespace) -> Faults:
    try:
        return Faults(
            garbage_rate_hz=args.garbage_rate, split=args.split, corrupt_prob=args.corrupt,
            drop_prob=args.drop, stalls=tuple(Window.parse(w) for w in args.stall),
            unplugs=tuple(Window.parse(w) for w in args.unplug),
        )
    except ValueError as err:
        raise UsageError(str(err)) from err


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve the built-in scenario on pseudo-terminals and print the paths to open."""
    faults = _faults(args)
    devices = [DeviceSpec(kind, _driver(name), faults)
               for kind, name in (("imu", args.imu), ("uwb", args.uwb)) if name != "none"]
    if not devices:
        raise UsageError("nothing to emulate: both --imu and --uwb are 'none'")
    link_dir = Path(args.link_dir) if args.link_dir else None
    if link_dir is not None:
        try:
            link_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UsageError(f"--link-dir {link_dir}: cannot create it: "
                             f"{err.strerror or err}") from err
    with Emulator(devices, CircleScenario(seed=args.seed), args.duration, link_dir) as emu:
        for dev in devices:
            port = emu.ports[dev.name]
            print(f"{dev.name} {dev.driver} {port.path} ({port.tty_path})", flush=True)
        emu.start()
        wait_until(emu.finished)
        with shielded():
            emu.close()
            print(json.dumps({name: vars(c) for name, c in emu.counts.items()}),
                  file=sys.stderr)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Emulated sensors through the pipeline, live in the terminal, until Ctrl-C."""
    live = _foxglove(args)
    with tempfile.TemporaryDirectory(prefix="uwbd-demo-") as tmp:
        return run_demo(Path(tmp), duration_s=args.duration, seed=args.seed, live=live)


FOXGLOVE_DEFAULT = "127.0.0.1:8765"


def _foxglove(args: argparse.Namespace) -> Callable[[Config], Any] | None:
    """``--foxglove [HOST:PORT]``: what starts the live Foxglove server for a config, from the
    ``foxglove`` extra (imported only then, so it never sits in the daemon's memory
    otherwise); ``None`` without the option."""
    if args.foxglove is None:
        return None
    try:
        from uwbd.service.live import FoxgloveLive, parse_endpoint
    except ImportError as err:
        raise UsageError(f"--foxglove needs the foxglove extra ({err.name} is missing): "
                         "pip install 'uwbd[foxglove]' (from a checkout: pip install "
                         "'.[foxglove]')") from err
    try:
        host, port = parse_endpoint(args.foxglove)
    except ValueError as err:
        raise UsageError(f"--foxglove {err}") from err

    def start(config: Config) -> Any:
        try:
            return FoxgloveLive(config, host, port)
        except RuntimeError as err:  # the SDK's FoxgloveError: the port is taken, no such host
            raise UsageError(f"--foxglove {args.foxglove}: cannot serve there: "
                             f"{str(err).removeprefix('FoxgloveError: ')}") from err
    return start


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run the simulator and write its log (raw device bytes + ground truth)."""
    out = Path(args.output)
    _writable_folder(out, "the log")
    driver = _driver(args.uwb)
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration {args.duration}: give a positive number of seconds")
    sim = simulate(SimConfig(seed=args.seed) if args.duration is None else
                   SimConfig(seed=args.seed, segments=segments_for(args.duration)))
    try:
        write_simulation(sim, out, driver)
    except OSError as err:
        out.unlink(missing_ok=True)  # half a log claims nothing
        raise RunError(f"cannot write {out}: {err.strerror or err}") from err
    duration = (sim.truth_t_ns[-1] - sim.truth_t_ns[0]) / 1e9
    print(f"{out}: {duration:.0f} s simulated, {len(sim.imu)} IMU samples, "
          f"{len(sim.uwb)} UWB epochs ({args.uwb}), seed {args.seed}")
    return 0


# dataset layout -> (loader, IMU mounting sensor -> body, IMU -> antenna lever arm m)
IMPORTERS: dict[str, tuple[Callable[[Path], Dataset], Sequence[Sequence[float]],
                           Sequence[float]]] = {
    "iasl": (load_iasl, Z_DOWN, (0.0, 0.0, 0.0)),
    "inrol": (load_inrol, INROL_MOUNTING, INROL_LEVER_ARM_M),
}


def cmd_import(args: argparse.Namespace) -> int:
    """Turn a recorded dataset into a replayable log with its ground truth."""
    directory, out = Path(args.directory), Path(args.output)
    _writable_folder(out, "the log")
    load, mounting, lever_arm_m = IMPORTERS[args.format]
    try:
        ds = load(directory)
    except DatasetError as err:
        raise UsageError(str(err)) from err
    try:
        write_dataset(ds, out, mounting, lever_arm_m, progress=sys.stderr.isatty())
    except OSError as err:
        out.unlink(missing_ok=True)  # half a log claims nothing
        raise RunError(f"cannot write {out}: {err.strerror or err}") from err
    # the loaders return every stream non-empty and in time order
    start = min(ds.imu[0].t_ns, ds.uwb[0].t_ns, int(ds.truth_t_ns[0]))
    end = max(ds.imu[-1].t_ns, ds.uwb[-1].t_ns, int(ds.truth_t_ns[-1]))
    print(f"{out}: {len(ds.imu)} IMU samples, {len(ds.uwb)} UWB messages "
          f"({sum(len(m.ranges) for m in ds.uwb)} ranges), {len(ds.truth_t_ns)} truth samples, "
          f"{(end - start) / 1e9:.1f} s from {directory}")
    return 0


def _open_log(name: str, doing: str) -> tuple[Path, LogContents]:
    """A log read for ``doing``; a log cut short by a crash is used up to its last chunk."""
    path = Path(name)
    if not path.exists():
        raise UsageError(f"cannot read {path}: no such file")
    problem = not_a_log(path)
    if problem:
        raise UsageError(problem)
    contents = read_log(path)
    if contents.truncated:
        LOG.warning("%s; %s what was complete", contents.error, doing)
    return path, contents


def _log_config(args: argparse.Namespace, path: Path, contents: LogContents) -> str | None:
    """The config to run a log with: the log's own, or ``-c``'s, with the ``--set`` items;
    ``None`` for the log's own unchanged."""
    if args.config:
        text = _read_text(Path(args.config))
    elif "config_toml" in contents.metadata:
        text = contents.metadata["config_toml"]
    else:
        raise UsageError(f"{path}: not a uwbd log (no uwbd metadata holding its config); "
                         "give the config to use with -c CONFIG")
    if not args.set and not args.config:
        return None
    try:
        return apply_overrides(text, args.set, args.config or f"{path} (metadata)")
    except ConfigError as err:
        raise UsageError(str(err)) from err


def _read_text(path: Path) -> str:
    try:
        return load_config(path).text
    except ConfigError as err:
        raise UsageError(str(err)) from err


def _replayable(path: Path, contents: LogContents) -> None:
    if not any(m.topic.startswith("/raw/") or m.topic in ("/imu", "/uwb")
               for m in contents.messages):
        raise UsageError(f"{path}: nothing to run (no /raw/*, /imu or /uwb messages; topics: "
                         f"{', '.join(sorted(contents.topics())) or 'none'})")


def cmd_report(args: argparse.Namespace) -> int:
    """Every method on one log, scored against its ground truth, with plots."""
    path, contents = _open_log(args.log, "reporting")
    config_toml = _log_config(args, path, contents)
    _replayable(path, contents)
    report = _tools_extra("report")  # before anything is made
    try:
        rec = load_recording(contents, str(path), config_toml)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    default = path.with_suffix("")
    out_dir = Path(args.out_dir) if args.out_dir else (
        default if default != path else path.with_name(path.name + "-report"))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"cannot write the plots into {out_dir}: {err.strerror or err}") from err
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise UsageError(f"cannot write the plots into {out_dir}: the folder is not writable")

    try:
        print(report(rec, out_dir, args.skip, progress=sys.stderr.isatty()))
    except OSError as err:
        raise RunError(f"cannot write the plots into {out_dir}: {err.strerror or err}") from err
    return 0


def _tools_extra(command: str) -> Any:
    """The report function, from the ``tools`` extra (matplotlib, scipy, filterpy), which the
    robot's install leaves out; imported here so it never sits in the daemon's memory."""
    try:
        from uwbd.tools.report import report
    except ImportError as err:
        raise UsageError(f"{command} needs the tools extra ({err.name} is missing): "
                         "pip install 'uwbd[tools]' (from a checkout: pip install '.[tools]')"
                         ) from err
    return report


def cmd_replay(args: argparse.Namespace) -> int:
    """A log's reads through the live pipeline; the poses to -o, a summary to stdout."""
    path, contents = _open_log(args.log, "replaying")
    config_toml = _log_config(args, path, contents)
    _replayable(path, contents)
    out = Path(args.output) if args.output else None
    if out is not None:
        _writable_folder(out, "the replayed log")
        if out.exists() and out.resolve() == path.resolve():
            raise UsageError(f"{out}: give another file to write, not the log itself")
    try:
        pipeline, poses = replay(contents, str(path), out, args.realtime,
                                 progress=sys.stderr.isatty(), config_toml=config_toml)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    log_errors = [str(getattr(sink, "error", "")) for sink in pipeline.sinks
                  if getattr(sink, "error", "")]
    print(f"{path}: {pipeline.poses} poses; filter {pipeline.filter.status}"
          + (f"; written to {out}" if out and not log_errors and out.is_file() else ""))
    if poses.poses:
        x, y, z = poses.poses[-1].position_m
        print(f"last pose ({x:.3f}, {y:.3f}, {z:.3f}) m")
    if out is not None and (log_errors or not out.is_file()):
        raise RunError(f"{out}: the replayed log is incomplete: "
                       f"{log_errors[0] if log_errors else 'the file was not written'}")
    return 0


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
    _writable_folder(target, "the recovered log")
    try:
        result = recover(source, target)
    except OSError as err:
        target.unlink(missing_ok=True)
        raise RunError(f"cannot write {target}: {err.strerror or err}") from err
    print(f"{target}: {result.messages} messages recovered from {source}"
          + (f" ({result.error})" if result.truncated else
             " (it was complete)"))
    return 0


def cmd_calibrate_imu(args: argparse.Namespace) -> int:
    """The accelerometer's scale and offset and the gyro's offset per axis from a six-position
    static capture (:mod:`uwbd.tools.imu_calibration`); ``-o`` writes them as an ``[imu]``
    snippet, ``--write-config`` into a copy of a config."""
    from drivers.frames import ImuSample
    from uwbd.config import parse as parse_config
    from uwbd.fusion.eskf import GRAVITY_MPS2
    from uwbd.tools.imu_calibration import MIN_STATIC_S, CalibrationError, calibrate

    if args.gravity is not None and not 9.7 <= args.gravity <= 9.9:
        raise UsageError(f"--gravity {args.gravity:g}: expected the local gravity, 9.7..9.9 "
                         "m/s²")
    if args.min_static is not None and not args.min_static > 0:
        raise UsageError(f"--min-static {args.min_static:g}: expected a positive number of s")
    path, contents = _open_log(args.log, "calibrating from")
    snippet = Path(args.output) if args.output else None
    if snippet is not None:
        _writable_folder(snippet, "the [imu] snippet")
    rewrite = None
    if args.write_config:
        base, out = Path(args.write_config[0]), Path(args.write_config[1])
        text = _read_text(base)  # the config must load as it is
        if out.exists() and out.resolve() == base.resolve():
            raise UsageError(f"{out}: give another file to write, not the config itself")
        _writable_folder(out, "the config")
        rewrite = (base, text, out)
    try:
        rec = load_recording(contents, str(path))
        logged_g = rec.config.imu_intrinsics.get("gravity_mps2")
    except ConfigError:  # only its IMU samples are needed
        rec, logged_g = load_recording(contents, str(path), ""), None
    imu = [f for f in rec.frames if isinstance(f, ImuSample)]
    if not imu:
        raise UsageError(f"{path}: no IMU samples (topics: "
                         f"{', '.join(sorted(contents.topics())) or 'none'})")
    gravity = args.gravity if args.gravity is not None else logged_g or GRAVITY_MPS2
    try:
        cal = calibrate(imu, gravity, MIN_STATIC_S if args.min_static is None
                        else args.min_static)
    except CalibrationError as err:
        raise UsageError(f"{path}: {err}") from err
    problems = cal.problems()
    if problems:
        raise UsageError(f"{path}: the capture gives {'; '.join(problems)}: not a sensor's "
                         "error (was it held still, in m/s²?)")
    print(cal.summary(str(path)))
    if snippet is not None:
        _write_atomically(snippet, cal.snippet(str(path)))
        print(f"wrote {snippet}: the [imu] keys (merge them into the config's [imu] section)")
    if rewrite is not None:
        base, text, out = rewrite
        try:
            new = apply_overrides(text, cal.overrides(), str(base))
            parse_config(new, str(out))
        except ConfigError as err:
            raise UsageError(str(err)) from err
        _write_atomically(out, new)
        print(f"wrote {out}: {base} with imu.acc_scale, acc_offset_mps2, gyro_offset_rps and "
              "gravity_mps2 set")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """A log as a ROS 2 bag folder (metadata.yaml + MCAP, CDR): see :mod:`uwbd.tools.ros2`."""
    path, contents = _open_log(args.log, "exporting")
    out = Path(args.ros2)
    if out.exists() or out.is_symlink():
        raise UsageError(f"cannot write the bag {out}: it exists (a bag is a new folder: "
                         "remove it or give another name)")
    _writable_folder(out, "the bag")
    config_toml = _log_config(args, path, contents)
    if config_toml is not None or not any(m.topic == "/pose" for m in contents.messages):
        _replayable(path, contents)  # the poses come from a replay
    try:
        from uwbd.tools.ros2 import export_ros2
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
    n = result.counts
    origin = "the log's own" if result.poses_from == "log" else "replayed"
    print(f"{out}: ROS 2 bag (MCAP) from {path}: {n.get('/uwbd/pose', 0)} poses ({origin}), "
          f"{n.get('/uwbd/imu', 0)} IMU samples, {n.get('/uwbd/truth', 0)} truth poses; "
          f"topics {', '.join(sorted(n))}")
    return 0


def cmd_survey(args: argparse.Namespace) -> int:
    """The anchors' positions from a log's ranges (anchor-to-anchor, a moving tag's, or both):
    :mod:`uwbd.tools.survey`; ``-o`` writes them as an ``[anchors]`` table,
    ``--write-config`` into a copy of a config."""
    from uwbd.config import parse as parse_config
    from uwbd.config.schema import anchor_id

    path, contents = _open_log(args.log, "surveying")
    config_toml = _log_config(args, path, contents)
    table_out = Path(args.output) if args.output else None
    if table_out is not None:
        _writable_folder(table_out, "the anchors")
        if table_out.exists() and table_out.resolve() == path.resolve():
            raise UsageError(f"{table_out}: give another file to write, not the log itself")
    rewrite = None
    if args.write_config:
        base, out = Path(args.write_config[0]), Path(args.write_config[1])
        text = _read_text(base)  # the config must load as it is
        if out.exists() and out.resolve() in (base.resolve(), path.resolve()):
            raise UsageError(f"{out}: give another file to write, not the "
                             f"{'config' if out.resolve() == base.resolve() else 'log'} itself")
        _writable_folder(out, "the config")
        rewrite = (base, text, out)
    if not 0 < args.prior_sigma < float("inf"):
        raise UsageError(f"--prior-sigma {args.prior_sigma:g}: expected a positive number of m")

    def anchor(option: str, value: str | None) -> int | None:
        if value is None:
            return None
        found = anchor_id(value.strip())
        if found is None:
            raise UsageError(f"{option} {value}: an anchor id is an integer of 0 or more "
                             "(3, 0x1151)")
        return found

    heights: dict[int, float] = {}
    for item in args.height:
        key, equals, value = item.partition("=")
        try:
            z = float(value)
        except ValueError:
            z = float("nan")
        height_of = anchor("--height", key) if equals else None
        if height_of is None or not -1e4 < z < 1e4:
            raise UsageError(f"--height {item}: expected ID=Z (anchor id, height in m: 3=2.45)")
        heights[height_of] = z
    try:
        from uwbd.tools.survey import (
            Gauge,
            Settings,
            SurveyError,
            anchors_document,
            log_ranges,
            survey,
            table,
            with_anchors,
        )
    except ImportError as err:
        raise UsageError(f"survey needs the tools extra ({err.name} is missing): pip install "
                         "'uwbd[tools]' (from a checkout: pip install '.[tools]')") from err
    where = f"{path} (metadata)" if config_toml is None else f"{path} (with -c/--set)"
    try:
        config = parse_config(contents.metadata.get("config_toml", "") if config_toml is None
                              else config_toml, where)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    uwb, pairs = log_ranges(contents)
    if not uwb and not pairs:
        raise UsageError(f"{path}: nothing to survey from: no UWB ranges (no tag ranges, no "
                         "anchor-to-anchor ranges; topics: "
                         f"{', '.join(sorted(contents.topics())) or 'none'})")
    fc = config.filter_config()
    settings = Settings(
        gauge=Gauge(anchor("--origin", args.origin), anchor("--x-axis", args.x_axis),
                    anchor("--y-side", args.y_side)),
        heights_m=heights, prior_sigma_m=args.prior_sigma, range_sigma_m=fc.range_sigma_m,
        range_offsets=args.range_offsets, offset_sigma_m=fc.range_bias_sigma_m,
        tag_side=fc.tag_side, height_range_m=fc.height_range_m,
        max_range_m=fc.gating.max_range_m)
    try:
        result = survey(config.anchors_m, uwb, pairs, settings)
    except SurveyError as err:
        raise UsageError(f"{path}: {err}") from err
    print(_survey_summary(str(path), result, fc.range_sigma_m))
    print(table(result))
    for note in result.notes:
        print(f"note: {note}")
    header = (f"[anchors] surveyed by `uwbd survey` from {path} ({result.source})\n"
              f"frame: {result.gauge}")
    if table_out is not None:
        _write_atomically(table_out, anchors_document(result, header))
        print(f"wrote {table_out}: the surveyed [anchors] table (replace the config's with it)")
    if rewrite is not None:
        base, text, out = rewrite
        try:
            new = with_anchors(text, result, f"{base} with its {header}", str(base))
        except SurveyError as err:
            raise UsageError(str(err)) from err
        _write_atomically(out, new)
        print(f"wrote {out}: {base} with the surveyed anchors (its comments are not kept)")
    return 0


def _survey_summary(where: str, result: Any, range_sigma_m: float) -> str:
    lines = [f"{where}: {len(result.anchors)} anchors from {result.source}"
             + (f": {result.tag_ranges} tag ranges at {result.tag_positions} tag positions"
                if result.tag_ranges else "")
             + (f"; {len(result.pairs)} anchor pairs ({sum(p.n for p in result.pairs)} ranges, "
                "median of each)" if result.pairs else "")
             + f"; {result.seconds:.1f} s", f"frame: {result.gauge}"]
    if result.tag_ranges:
        lines.append(f"tag ranges: robust RMS residual {result.residual_rms_m:.3f} m "
                     f"({result.sigma0:.2f} x the config's range σ {range_sigma_m:g} m); "
                     f"{result.downweighted} more than 3 σ off, down-weighted (NLOS?)")
    lines.append(f"1-σ (RMS over the anchors, 3-D): {result.layout_sigma_m:.3f} m for the "
                 "anchors relative to each other"
                 + (f", {result.frame_sigma_m:.3f} m for where the layout sits"
                    + (" in height and tilt" if result.user_frame else "")
                    + " (the configured positions fix that: no range sees it)"
                    if result.frame_sigma_m > 0.0005 else ""))
    return "\n".join(lines)


def _write_atomically(target: Path, text: str) -> None:
    """``text`` into ``target`` whole or not at all (a temporary file renamed over it)."""
    tmp = None
    try:
        with tempfile.NamedTemporaryFile("w", encoding="utf-8", dir=target.parent,
                                         prefix=f".{target.name}.", delete=False) as f:
            tmp = Path(f.name)
            f.write(text)
        os.replace(tmp, target)
    except OSError as err:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise RunError(f"cannot write {target}: {err.strerror or err}") from err


def _load(path: str, warn: bool = False) -> Config:
    """A configuration file, or every problem with it, one line each naming file and key
    (exit 2); ``warn``: the warnings of a config that loads are said too."""
    try:
        config = load_config(Path(path))
    except ConfigError as err:
        raise UsageError(str(err)) from err
    if warn:
        for warning in config.warnings:
            LOG.warning("%s", warning)
    return config


def cmd_check_config(args: argparse.Namespace) -> int:
    """Validate a configuration file: its warnings, then every problem (exit 2) or one line
    saying it is fine."""
    try:
        config = load_config(Path(args.config))
    except ConfigError as err:
        for warning in err.warnings:
            LOG.warning("%s", warning)
        raise UsageError(str(err)) from err
    for warning in config.warnings:
        LOG.warning("%s", warning)
    ports = ", ".join(f"{s.name}={s.driver}@{s.port}" for s in config.sources) or "no sources"
    mode = config.filter_config().mode.value
    print(f"{args.config}: ok ({ports}; {len(config.anchors_m)} anchors; {mode} fusion"
          + (f"; {len(config.warnings)} warning(s) above)" if config.warnings else ")"))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """The daemon: serial ports → fusion → MCAP logs, until SIGINT/SIGTERM."""
    config = _load(args.config, warn=True)
    if not config.sources:
        raise UsageError(f"{args.config}: sources: at least one [[sources]] is needed")
    log_dir = Path(args.log_dir or config.log.get("directory", "logs"))
    live = _foxglove(args)
    extra = (live(config),) if live is not None else ()
    try:
        pipeline = asyncio.run(run_daemon(config, log_dir, args.duration, extra_sinks=extra,
                                          summary_s=args.summary_every, where=args.config))
    except PipelineError as err:
        raise RunError(str(err)) from err
    finally:
        for sink in extra:  # the pipeline closes its sinks; this is for a run that never began
            sink.close()
    sources = pipeline.extra_status.get("sources", {})
    if sources and not any(s["opens"] for s in sources.values()):
        raise RunError("no port could be opened: " + "; ".join(
            f"{name}: {s['last_error']}" for name, s in sources.items()))
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    """Print the poses (or status) a daemon publishes."""
    zcfg: dict[str, Any] = {"mode": "peer", "multicast_scouting": not args.connect}
    prefix = args.prefix
    if args.config:
        config = _load(args.config)
        # dial the daemon: its routers, and its own listen endpoints (a subscriber must not
        # take the daemon's listen port itself)
        zenoh_cfg = config.zenoh
        dial = [*zenoh_cfg.get("connect", []), *dial_endpoints(zenoh_cfg.get("listen", []))]
        zcfg.update(multicast_scouting=zenoh_cfg.get("multicast_scouting", True),
                    connect=dial)
        prefix = prefix or config.zenoh_prefix
    if args.connect:
        zcfg["connect"] = [*args.connect, *zcfg.get("connect", [])]
    prefix = str(prefix or f"uwbd/{default_robot_name()}")
    if zcfg.get("connect"):
        # it dials a daemon or a router and only listens: as a client it needs no listen
        # endpoint of its own, which a peer would (peers mesh with each other directly)
        zcfg["mode"] = "client"
    try:
        zenoh.KeyExpr(f"{prefix.strip('/')}/pose")
    except zenoh.ZError as err:
        raise UsageError(f"--prefix {prefix}: not a key expression ({zenoh_reason(err)}); "
                         "e.g. uwbd/robot1 or uwbd/*") from err
    try:
        printed = echo(zcfg, prefix, args.status, args.count, args.timeout)
    except EchoError as err:
        raise RunError(str(err)) from err
    if args.timeout is not None and printed == 0:
        raise RunError(f"nothing received on {prefix}/{'status' if args.status else 'pose'} "
                       f"in {args.timeout:g} s")
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    """A Zenoh router for several daemons (as ``zenohd``)."""
    try:
        run_router(args.listen or [DEFAULT_LISTEN], args.multicast_scouting)
    except RouterError as err:
        raise UsageError(str(err)) from err
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="uwbd", description=__doc__.splitlines()[0])
    ap.add_argument("--version", action="version",
                    version=f"uwbd {__version__} (fusion: {native.implementation})")
    talk = argparse.ArgumentParser(add_help=False)
    talk.add_argument("-v", "--verbose", action="count", default=0,
                      help="say more (debug lines)")
    talk.add_argument("-q", "--quiet", action="count", default=0,
                      help="only warnings and errors")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, **kw: Any) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[talk], **kw)

    p = add("dump", help="decode a byte capture as JSON lines")
    p.add_argument("--driver", required=True, help=f"one of: {', '.join(PARSERS)}")
    p.add_argument("file", help="capture file, or - for standard input")
    p.set_defaults(func=cmd_dump)

    p = add("emulate", help="serve emulated devices on pseudo-terminals")
    p.add_argument("--imu", default="wit", help="IMU driver, or none (default: wit)")
    p.add_argument("--uwb", default="nlink",
                   help=f"UWB driver, or none; one of {', '.join(set(ENCODERS) - {'wit'})}")
    _common(p)
    p.add_argument("--link-dir", help="create stable names DIR/imu and DIR/uwb for the ports")
    p.add_argument("--garbage-rate", type=float, default=0.0, metavar="HZ",
                   help="mean rate of garbage bursts")
    p.add_argument("--split", action="store_true", help="split frames at random byte boundaries")
    p.add_argument("--corrupt", type=float, default=0.0, metavar="P",
                   help="probability a frame has a flipped byte")
    p.add_argument("--drop", type=float, default=0.0, metavar="P",
                   help="probability a frame is dropped")
    p.add_argument("--stall", action="append", default=[], metavar="AT:DUR",
                   help="send nothing from AT for DUR seconds (repeatable)")
    p.add_argument("--unplug", action="append", default=[], metavar="AT:DUR",
                   help="close the port at AT for DUR seconds (repeatable)")
    p.set_defaults(func=cmd_emulate)

    p = add("run", help="the daemon: serial ports -> fusion -> MCAP")
    p.add_argument("-c", "--config", required=True, help="configuration TOML")
    p.add_argument("--log-dir", help="where logs go (default: [log] directory, or ./logs)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--summary-every", type=float, default=60.0, metavar="S",
                   help="log a one-line health summary every S seconds (default 60)")
    _foxglove_option(p)
    p.set_defaults(func=cmd_run)

    p = add("check-config", help="validate a configuration file")
    p.add_argument("config")
    p.set_defaults(func=cmd_check_config)

    p = add("echo", help="print the poses (or --status) a daemon publishes")
    p.add_argument("--status", action="store_true", help="status instead of poses")
    p.add_argument("--prefix", help="key prefix (default: from -c, else uwbd/<hostname>)")
    p.add_argument("-c", "--config", help="take the [zenoh] settings from this config")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="e.g. tcp/192.168.1.10:7447 (repeatable); default: scouting")
    p.add_argument("--count", type=int, help="stop after N messages")
    p.add_argument("--timeout", type=float, metavar="S", help="stop after S seconds")
    p.set_defaults(func=cmd_echo)

    p = add("router", help="a Zenoh router for a fleet of daemons (as zenohd)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"where daemons and subscribers connect (default {DEFAULT_LISTEN}; "
                   "repeatable)")
    p.add_argument("--multicast-scouting", action="store_true",
                   help="also answer multicast scouting on the LAN (default off)")
    p.set_defaults(func=cmd_router)

    p = add("replay", help="re-run a log through the same pipeline")
    p.add_argument("log")
    p.add_argument("-o", "--output", help="write the replayed run (raw, frames, poses) here")
    p.add_argument("--realtime", action="store_true", help="pace by the log's times")
    _tuning(p)
    p.set_defaults(func=cmd_replay)

    p = add("recover", help="rewrite a log cut short by a crash as a valid MCAP file")
    p.add_argument("log")
    p.add_argument("-o", "--output", required=True, help="the MCAP file to write")
    p.set_defaults(func=cmd_recover)

    p = add("export", help="write a log as a ROS 2 bag (pose, odometry, IMU, TF, truth)",
            description="Write a log as a ROS 2 bag folder (metadata.yaml + one MCAP file, "
            "CDR): /uwbd/pose, /uwbd/odom, /uwbd/imu, /tf, /tf_static and /uwbd/truth (if "
            "the log has truth), frame names from the config's [robot] section. The poses "
            "are the log's own /pose; with -c or --set, or for a log without poses (a "
            "simulated or imported one), the log is replayed with that config to make them.")
    p.add_argument("log")
    p.add_argument("--ros2", required=True, metavar="OUT",
                   help="the bag folder to create (it must not exist)")
    _tuning(p)
    p.set_defaults(func=cmd_export)

    p = add("simulate", help="simulate a run and write its MCAP log")
    p.add_argument("-o", "--output", default="sim.mcap", help="log to write (default sim.mcap)")
    p.add_argument("--uwb", default="nlink", help="UWB wire format in the log (default nlink)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, metavar="S",
                   help="length of the run: the default path (59 s) cut or repeated")
    p.set_defaults(func=cmd_simulate)

    p = add("import", help="turn a recorded dataset into an MCAP log")
    p.add_argument("format", choices=list(IMPORTERS), help="dataset layout")
    p.add_argument("directory", help="dataset folder (iasl: imu.csv, uwb.csv, gt.csv; "
                   "inrol: anchor.txt, imu.txt, uwb.txt, imu_pose.txt)")
    p.add_argument("-o", "--output", default="import.mcap")
    p.set_defaults(func=cmd_import)

    p = add("report", help="compare all methods on a log against its ground truth")
    p.add_argument("log")
    p.add_argument("-o", "--out-dir", help="where the plots go (default: next to the log)")
    p.add_argument("--skip", type=float, default=0.0, metavar="S",
                   help="leave the first S seconds of truth out of the scores")
    _tuning(p)
    p.set_defaults(func=cmd_report)

    p = add("calibrate-imu", help="IMU scale and offsets from a six-position static capture",
            description="Compute the accelerometer's scale and offset and the gyro's offset "
            "per sensor axis (a_true = (a_meas - acc_offset_mps2) / acc_scale) from a log of "
            "the IMU held still with each axis up and then down in turn, a few seconds each, "
            "in any order; print them with their uncertainties.")
    p.add_argument("log")
    _config_outputs(p, "the [imu] keys found as a TOML snippet",
                    "with the [imu] keys set")
    p.add_argument("--gravity", type=float, metavar="MPS2",
                   help="local gravity, m/s² (default: the log's imu.gravity_mps2, else "
                   "9.80665)")
    p.add_argument("--min-static", type=float, metavar="S",
                   help="shortest still segment used, s (default 1.5)")
    p.set_defaults(func=cmd_calibrate_imu)

    p = add("survey", help="the anchors' positions from a log's ranges",
            description="Estimate the anchor positions from a log: from anchor-to-anchor "
            "ranges (TREK1000 ma reports) by multilateration, and from a moving tag's ranges "
            "by one robust least-squares adjustment of the tag's path and the anchors, "
            "starting from the config's anchors; print them with their 1-sigma and the "
            "change from the config. By default each configured position counts as a "
            "measurement (--prior-sigma): the output stays in the config's frame; "
            "--origin/--x-axis/--y-side put it in the frame those anchors define.")
    p.add_argument("log")
    _config_outputs(p, "the surveyed [anchors] table as a TOML file",
                    "with its [anchors] replaced by the surveyed ones")
    p.add_argument("--origin", metavar="ID", help="this anchor is at x = y = 0")
    p.add_argument("--x-axis", metavar="ID", help="this anchor is on the +x axis (y = 0)")
    p.add_argument("--y-side", metavar="ID",
                   help="this anchor is on the +y side (default: the side the config puts "
                   "the anchors on)")
    p.add_argument("--height", action="append", default=[], metavar="ID=Z",
                   help="hold this anchor's height at Z m (repeatable); anchor-to-anchor "
                   "ranges between anchors on one plane take the heights from the config")
    p.add_argument("--prior-sigma", type=float, default=0.2, metavar="M",
                   help="how far the configured positions may be off, 1-sigma per axis "
                   "(default 0.2 m)")
    p.add_argument("--range-offsets", action="store_true",
                   help="also estimate a range offset per anchor (its antenna delay; "
                   "printed, not written)")
    _tuning(p)
    p.set_defaults(func=cmd_survey)

    p = add("demo", help="emulated sensors through drivers and fusion, live poses")
    _common(p)
    _foxglove_option(p)
    p.set_defaults(func=cmd_demo)
    return ap


def _foxglove_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--foxglove", nargs="?", const=FOXGLOVE_DEFAULT, default=None,
                   metavar="HOST:PORT",
                   help=f"serve the channels live to Foxglove over its WebSocket protocol "
                        f"(default {FOXGLOVE_DEFAULT}: this machine only; 0.0.0.0:PORT serves "
                        "the network); needs the foxglove extra")


def _config_outputs(p: argparse.ArgumentParser, snippet: str, changed: str) -> None:
    """``-o FILE`` (a TOML snippet) and ``--write-config CONFIG OUT`` (the whole config)."""
    p.add_argument("-o", "--output", metavar="FILE", help=f"write {snippet}")
    p.add_argument("--write-config", nargs=2, metavar=("CONFIG", "OUT"),
                   help=f"write CONFIG {changed} as OUT (its comments are not kept)")


def _tuning(p: argparse.ArgumentParser) -> None:
    p.add_argument("-c", "--config", help="run with this config instead of the log's own")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="change one setting, e.g. --set fusion.zupt=false (repeatable)")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: run until Ctrl-C)")
    p.add_argument("--seed", type=int, default=0, help="scenario and fault seed")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    log = journal.setup(args.command, args.verbose - args.quiet)
    try:
        return int(args.func(args))
    except UsageError as err:
        for line in str(err).splitlines():  # a config may have several problems
            log.error("%s", line)
        return 2
    except RunError as err:
        log.error("%s", err)
        return 1
    except BrokenPipeError:
        quiet_stdout()  # output piped into e.g. `head`: not an error
        return 0
    except KeyboardInterrupt:  # interrupted before the command was ready to stop cleanly
        return 130
    except Exception as err:  # a bug: one line (the traceback with -v), exit 1
        log.error("internal error: %s: %s (run again with -v for the traceback, and please "
                  "report it)", type(err).__name__, err, exc_info=True)
        return 1

