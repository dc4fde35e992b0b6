"""The offline tools' commands: ``simulate``, ``import``, ``report``, ``calibrate-imu``,
``survey``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uwbd.commands.common import (
    ConfigRewrite,
    RunError,
    UsageError,
    driver_name,
    log_config,
    open_log,
    require_replayable,
    tools_report,
    writable_folder,
    write_atomically,
    written,
)
from uwbd.config import ConfigError
from uwbd.tools.importer import Dataset, DatasetError, load_iasl, load_inrol
from uwbd.tools.logtools import load_recording, write_dataset, write_simulation
from uwbd.tools.sim_presets import segments_for
from uwbd.tools.simulator import SimConfig, simulate


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run the simulator and write its log (raw device bytes + ground truth)."""
    out = Path(args.output)
    writable_folder(out, "the log")  # (before the simulation's work)
    driver = driver_name(args.uwb)
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration {args.duration}: give a positive number of seconds")
    sim = simulate(SimConfig(seed=args.seed) if args.duration is None else
                   SimConfig(seed=args.seed, segments=segments_for(args.duration)))
    with written(out, "the log") as tmp:  # half a log claims nothing
        write_simulation(sim, tmp, driver)
    duration = (sim.truth_t_ns[-1] - sim.truth_t_ns[0]) / 1e9
    print(f"{out}: {duration:.0f} s simulated, {len(sim.imu)} IMU samples, "
          f"{len(sim.uwb)} UWB epochs ({args.uwb}), seed {args.seed}")
    return 0


# dataset layout -> its loader (which says the IMU's mounting and lever arm)
IMPORTERS: dict[str, Callable[[Path], Dataset]] = {"iasl": load_iasl, "inrol": load_inrol}


def cmd_import(args: argparse.Namespace) -> int:
    """Turn a recorded dataset into a replayable log with its ground truth."""
    directory, out = Path(args.directory), Path(args.output)
    writable_folder(out, "the log")
    try:
        ds = IMPORTERS[args.format](directory)
    except DatasetError as err:
        raise UsageError(str(err)) from err
    with written(out, "the log") as tmp:  # half a log claims nothing
        write_dataset(ds, tmp, ds.mounting, ds.lever_arm_m, progress=sys.stderr.isatty())
    # the loaders return ranges and truth non-empty, every stream in time order
    starts = [ds.uwb[0].t_ns, int(ds.truth_t_ns[0])] + [f.t_ns for f in ds.imu[:1]]
    ends = [ds.uwb[-1].t_ns, int(ds.truth_t_ns[-1])] + [f.t_ns for f in ds.imu[-1:]]
    start, end = min(starts), max(ends)
    print(f"{out}: " + (f"{len(ds.imu)} IMU samples" if ds.imu else
                        "no IMU (a range-model calibration recording: calibrate-ranges)")
          + f", {len(ds.uwb)} UWB messages "
          f"({sum(len(m.ranges) for m in ds.uwb)} ranges), {len(ds.truth_t_ns)} truth samples, "
          f"{(end - start) / 1e9:.1f} s from {directory}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Every method on one log, scored against its ground truth, with plots."""
    path, contents = open_log(args.log, "reporting")
    config_toml = log_config(args, path, contents)
    require_replayable(path, contents)
    report = tools_report("report")  # before anything is made
    try:
        rec = load_recording(contents, str(path), config_toml)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    default = path.with_suffix("")
    out_dir = Path(args.out_dir) if args.out_dir else (
        default if default != path else path.with_name(path.name + "-report"))
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"cannot write the plots into {out_dir}: it is not a folder; give a "
                         "folder's path (made if missing)")
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


def cmd_calibrate_imu(args: argparse.Namespace) -> int:
    """The accelerometer's scale and offset and the gyro's offset per axis from a six-position
    static capture (:mod:`uwbd.tools.imu_calibration`); ``-o`` writes them as an ``[imu]``
    snippet, ``--write-config`` into a copy of a config."""
    from drivers.frames import ImuSample
    from uwbd.fusion.core.noise import GRAVITY_MPS2
    from uwbd.tools.imu_calibration import MIN_STATIC_S, CalibrationError, calibrate

    if args.gravity is not None and not 9.7 <= args.gravity <= 9.9:
        raise UsageError(f"--gravity {args.gravity:g}: expected the local gravity, 9.7..9.9 "
                         "m/s²")
    if args.min_static is not None and not args.min_static > 0:
        raise UsageError(f"--min-static {args.min_static:g}: expected a positive number of s")
    path, contents = open_log(args.log, "calibrating from")
    snippet = Path(args.output) if args.output else None
    if snippet is not None:
        writable_folder(snippet, "the [imu] snippet")
    rewrite = ConfigRewrite.of(args)
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
        write_atomically(snippet, cal.snippet(str(path)))
        print(f"wrote {snippet}: the [imu] keys (merge them into the config's [imu] section)")
    if rewrite is not None:
        rewrite.write(cal.overrides(), "imu.acc_scale, acc_offset_mps2, gyro_offset_rps and "
                      "gravity_mps2 set")
    return 0


def cmd_calibrate_ranges(args: argparse.Namespace) -> int:
    """The range model (the tag antenna's direction term, the anchors' delays) from a log
    with ground truth (:mod:`uwbd.tools.range_calibration`); ``-o`` writes the keys as a
    snippet, ``--write-config`` into a copy of a config."""
    path, contents = open_log(args.log, "calibrating from")
    config_toml = log_config(args, path, contents)
    snippet = Path(args.output) if args.output else None
    if snippet is not None:
        writable_folder(snippet, "the [range_model] snippet")
    rewrite = ConfigRewrite.of(args, path)
    try:
        from uwbd.tools.range_calibration import (
            RangeCalibrationError,
            calibrate,
            range_samples,
        )
    except ImportError as err:
        raise UsageError(f"calibrate-ranges needs the tools extra ({err.name} is missing): pip "
                         "install 'uwbd[tools]' (from a checkout: pip install '.[tools]')") from err
    try:
        rec = load_recording(contents, str(path), config_toml)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    if not len(rec.truth_t_ns):
        raise UsageError(f"{path}: no ground truth (/truth): a range calibration needs the "
                         "tag's or the IMU's true pose (record under motion capture; `uwbd "
                         "import` keeps a dataset's)")
    c, model = rec.config, rec.config.range_model_settings()
    try:
        samples = range_samples(rec.frames, c.anchors_m, rec.truth_t_ns, rec.truth_p_m,
                                rec.truth_rotation, c.lever_arm_m, model.tag_mounting,
                                c.anchor_axes)
        cal = calibrate(samples, args.degree,
                        oriented=not np.allclose(rec.truth_rotation, np.eye(3)),
                        anchor_degree=args.anchor_degree)
    except RangeCalibrationError as err:
        raise UsageError(f"{path}: {err}") from err
    mounted = ("tag axes = body axes" if np.allclose(model.tag_mounting, np.eye(3))
               else "tag axes by range_model.tag_mounting")
    print(cal.summary(str(path), mounted))
    delays = not args.no_anchor_delays
    fusion = [f"fusion.{k}" for k in cal.keys(delays).get("fusion", {})]
    also = f" and {', '.join(fusion)}" if fusion else ""
    if snippet is not None:
        write_atomically(snippet, cal.snippet(str(path), delays))
        print(f"wrote {snippet}: the [range_model] keys{also} (merge them into the config)")
    if rewrite is not None:
        rewrite.write(cal.overrides(str(path), delays), f"its [range_model] set{also}")
    return 0


def cmd_survey(args: argparse.Namespace) -> int:
    """The anchors' positions from a log's ranges (anchor-to-anchor, a moving tag's, or both):
    :mod:`uwbd.tools.survey`; ``-o`` writes them as an ``[anchors]`` table,
    ``--write-config`` into a copy of a config."""
    from uwbd.config import parse as parse_config
    from uwbd.config.schema import anchor_id

    path, contents = open_log(args.log, "surveying")
    config_toml = log_config(args, path, contents)
    table_out = Path(args.output) if args.output else None
    if table_out is not None:
        writable_folder(table_out, "the anchors")
        if table_out.exists() and table_out.resolve() == path.resolve():
            raise UsageError(f"{table_out}: give another file to write, not the log itself")
    rewrite = ConfigRewrite.of(args, path)
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
            orientations_of,
            survey,
            table,
            with_anchors,
            without_distance_term,
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
    k = fc.range_model.log_distance_m
    if k:
        uwb, pairs = without_distance_term(fc.range_model, uwb, pairs)
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
    if k:
        print(f"the ranges' distance term taken off first (range_model.log_distance_m = {k:g})")
    print(table(result))
    for note in result.notes:
        print(f"note: {note}")
    header = (f"[anchors] surveyed by `uwbd survey` from {path} ({result.source})\n"
              f"frame: {result.gauge}")
    if table_out is not None:
        write_atomically(table_out, anchors_document(result, header,
                                                     orientations_of(config.text)))
        print(f"wrote {table_out}: the surveyed [anchors] table (replace the config's with it)")
    if rewrite is not None:
        try:
            new = with_anchors(rewrite.text, result, f"{rewrite.base} with its {header}",
                               str(rewrite.base))
        except SurveyError as err:
            raise UsageError(str(err)) from err
        write_atomically(rewrite.out, new)
        print(f"wrote {rewrite.out}: {rewrite.base} with the surveyed anchors (its comments "
              "are not kept)")
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
