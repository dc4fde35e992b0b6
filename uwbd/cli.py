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
import importlib
from collections.abc import Sequence
from typing import Any

from drivers import PARSERS
from uwbd import __version__, journal
from uwbd.commands.common import (
    FOXGLOVE_DEFAULT,
    ROS2_ROUTER_DEFAULT,
    ROUTER_LISTEN_DEFAULT,
    RunError,
    UsageError,
)
from uwbd.fusion.core import native
from uwbd.service.interrupt import quiet_stdout

IMPORT_FORMATS = ("iasl", "inrol")  # uwbd.commands.tools.IMPORTERS' keys


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="uwbd", description=(
        "The UWB + IMU localisation daemon and its tools: one subcommand per job."))
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
    p.set_defaults(func="logs:cmd_dump")

    p = add("emulate", help="serve emulated devices on pseudo-terminals")
    p.add_argument("--imu", default="wit", help="IMU driver, or none (default: wit)")
    p.add_argument("--uwb", default="nlink",
                   help=f"UWB driver, or none; one of {', '.join(sorted(set(PARSERS) - {'wit'}))} "
                        "(every driver's device is emulated)")
    _common(p)
    p.add_argument("--link-dir", help="create stable names DIR/imu and DIR/uwb for the ports")
    p.add_argument("--rest", type=float, default=2.0, metavar="S",
                   help="the vehicle stands still this long before it drives its circle "
                        "(default 2; a daemon that starts later joins a steady turn, which "
                        "does not tell the heading, and stays aligning)")
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
    p.set_defaults(func="service:cmd_emulate")

    p = add("run", help="the daemon: serial ports -> fusion -> MCAP")
    p.add_argument("-c", "--config", required=True, help="configuration TOML")
    p.add_argument("--log-dir", help="where logs go (default: [log] directory, or ./logs)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--summary-every", type=float, default=60.0, metavar="S",
                   help="log a one-line health summary every S seconds (default 60)")
    _foxglove_option(p)
    p.set_defaults(func="service:cmd_run")

    p = add("check-config", help="validate a configuration file")
    p.add_argument("config")
    p.set_defaults(func="config:cmd_check_config")

    p = add("echo", help="print the poses (or --status) a daemon publishes")
    p.add_argument("--status", action="store_true", help="status instead of poses")
    p.add_argument("--prefix", help="key prefix (default: from -c, else uwbd/<hostname>)")
    p.add_argument("-c", "--config", help="take the [zenoh] settings from this config")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="e.g. tcp/192.168.1.10:7447 (repeatable); default: a daemon on this host, "
                   "tcp/127.0.0.1:7447")
    p.add_argument("--ros2", nargs="?", const="", metavar="TOPIC",
                   help="the ROS 2 topic instead, decoded as a ROS 2 node would get it "
                   "(default: the pose topic, /uwbd/pose; domain and names from -c's [ros2])")
    p.add_argument("--count", type=int, help="stop after N messages")
    p.add_argument("--timeout", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="a Zenoh config file (JSON5) for this subscriber: its TLS certificates "
                   "or user and password (default: -c's zenoh.config, if any)")
    p.set_defaults(func="service:cmd_echo")

    p = add("router", help="a Zenoh router for a fleet of daemons (as zenohd)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"where daemons and subscribers connect (default {ROUTER_LISTEN_DEFAULT}; "
                   "repeatable)")
    p.add_argument("--multicast-scouting", action="store_true",
                   help="also answer multicast scouting on the LAN (default off)")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="a Zenoh config file (JSON5): TLS, authentication, access control "
                   "(docs/security.md)")
    p.set_defaults(func="service:cmd_router")

    p = add("replay", help="re-run a log through the same pipeline")
    p.add_argument("log")
    p.add_argument("-o", "--output", help="write the replayed run (raw, frames, poses) here")
    p.add_argument("--realtime", action="store_true", help="pace by the log's times")
    _tuning(p)
    p.set_defaults(func="logs:cmd_replay")

    p = add("recover", help="rewrite a log cut short by a crash as a valid MCAP file")
    p.add_argument("log")
    p.add_argument("-o", "--output", required=True, help="the MCAP file to write")
    p.set_defaults(func="logs:cmd_recover")

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
    p.set_defaults(func="logs:cmd_export")

    p = add("simulate", help="simulate a run and write its MCAP log")
    p.add_argument("-o", "--output", default="sim.mcap", help="log to write (default sim.mcap)")
    p.add_argument("--uwb", default="nlink", help="UWB wire format in the log (default nlink)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, metavar="S",
                   help="length of the run: the default path (59 s) cut or repeated")
    p.set_defaults(func="tools:cmd_simulate")

    p = add("import", help="turn a recorded dataset into an MCAP log")
    p.add_argument("format", choices=IMPORT_FORMATS, help="dataset layout")
    p.add_argument("directory", help="dataset folder (iasl: imu.csv, uwb.csv, gt.csv; "
                   "inrol: anchor.txt, imu.txt, uwb.txt, imu_pose.txt)")
    p.add_argument("-o", "--output", default="import.mcap")
    p.set_defaults(func="tools:cmd_import")

    p = add("report", help="compare all methods on a log against its ground truth")
    p.add_argument("log")
    p.add_argument("-o", "--out-dir", help="where the plots go (default: next to the log)")
    p.add_argument("--skip", type=float, default=0.0, metavar="S",
                   help="leave the first S seconds of truth out of the scores")
    _tuning(p)
    p.set_defaults(func="tools:cmd_report")

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
    p.set_defaults(func="tools:cmd_calibrate_imu")

    p = add("calibrate-ranges", help="the range model from a log with ground truth",
            description="Fit the tag antenna's direction-dependent delay (real spherical "
            "harmonics of the ray in the tag's axes), the delay that grows with the "
            "distance (k ln(d / 1 m)) and each anchor's antenna delay to a "
            "log with ground truth (/truth: the tag's pose, or the IMU's with the config's "
            "lever arm), by robust maximum likelihood; print each coefficient with its "
            "sigma, every degree's held-out check (fitted on the first 70 %%, scored on the "
            "rest) and the noise left. Record about 90 s, the tag turned through every "
            "heading, near and far from every anchor.")
    p.add_argument("log")
    _config_outputs(p, "the [range_model] keys found as a TOML snippet",
                    "with the [range_model] keys set")
    p.add_argument("--degree", type=int, default=1, choices=range(0, 4),
                   help="of the tag's term: 1 (default: a phase centre) to 3; 0 for none "
                   "(the anchors' delays and the distance term alone)")
    p.add_argument("--anchor-degree", type=int, default=0, choices=range(0, 4),
                   help="of the anchors' own direction term (the ray in each anchor's axes: "
                   "[anchors] entries with orientation_xyzw); 0 (default): none")
    p.add_argument("--no-anchor-delays", action="store_true",
                   help="write no anchor delays (the robot's anchors are other units than "
                   "the calibration's: the filter's delay states estimate theirs)")
    _tuning(p)
    p.set_defaults(func="tools:cmd_calibrate_ranges")

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
    p.set_defaults(func="tools:cmd_survey")

    p = add("demo", help="emulated sensors through drivers and fusion, live poses")
    _common(p)
    _foxglove_option(p)
    p.add_argument("--ros2", nargs="?", const=ROS2_ROUTER_DEFAULT, default=None,
                   metavar="ENDPOINT",
                   help="also publish the ROS 2 topics (rmw_zenoh), connected to the ROS 2 "
                   f"router there (default {ROS2_ROUTER_DEFAULT}, where rmw_zenohd listens); "
                   "needs the ros2 extra")
    p.set_defaults(func="service:cmd_demo")
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
        # "module:function" of uwbd.commands: only the command given is imported
        module, name = args.func.split(":")
        command = getattr(importlib.import_module(f"uwbd.commands.{module}"), name)
        return int(command(args))
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
