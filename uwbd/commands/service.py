"""The commands of the robot's daemon and its company: ``run``, ``demo``, ``emulate``,
``echo``, ``router``, ``check-config``."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import zenoh

from drivers.emulator import DeviceSpec, Emulator, Faults, Window
from drivers.emulator.scenario import CircleScenario
from uwbd.commands.common import (
    ROUTER_LISTEN_DEFAULT,
    RunError,
    UsageError,
    driver_name,
    foxglove_server,
    load_config_file,
)
from uwbd.config import default_robot_name, endpoint_problem
from uwbd.config.checks import Report
from uwbd.config.model import LOG_DIRECTORY
from uwbd.config.ros2 import (
    DEFAULT_TOPICS,
    EXTRA_HINT,
    TOPIC_NAME,
    Ros2Settings,
    missing_extra,
    settings_of,
)
from uwbd.config.zenoh_checks import check_zenoh_file
from uwbd.config.zenoh_session import THIS_HOST_LISTEN, effective, zenoh_reason
from uwbd.service.daemon import PipelineError, ZenohStartError
from uwbd.service.daemon import run as run_daemon
from uwbd.service.demo import run_demo
from uwbd.service.echo import EchoError, Listen, dial_endpoints, echo, uwbd_keys
from uwbd.service.interrupt import shielded, wait_until
from uwbd.service.router import RouterError, run_router


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve the built-in scenario on pseudo-terminals and print the paths to open."""
    faults = _faults(args)
    devices = [DeviceSpec(kind, driver_name(name), faults)
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
    if not 0.0 <= args.rest <= 3600.0:
        raise UsageError(f"--rest {args.rest:g}: seconds from 0 to 3600")
    scenario = CircleScenario(seed=args.seed, rest_s=args.rest)
    with Emulator(devices, scenario, args.duration, link_dir) as emu:
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


def _faults(args: argparse.Namespace) -> Faults:
    try:
        return Faults(
            garbage_rate_hz=args.garbage_rate, split=args.split, corrupt_prob=args.corrupt,
            drop_prob=args.drop, stalls=tuple(Window.parse(w) for w in args.stall),
            unplugs=tuple(Window.parse(w) for w in args.unplug),
        )
    except ValueError as err:
        raise UsageError(str(err)) from err


def cmd_demo(args: argparse.Namespace) -> int:
    """Emulated sensors through the pipeline, live in the terminal, until Ctrl-C."""
    live = foxglove_server(args)
    if args.ros2 is not None:
        missing = missing_extra()
        if missing is not None:
            raise UsageError(f"demo --ros2 needs the ros2 extra ({missing} is missing): "
                             f"{EXTRA_HINT}")
        problem = endpoint_problem(args.ros2)
        if problem is not None:
            raise UsageError(f"--ros2 {args.ros2}: {problem}")
    with tempfile.TemporaryDirectory(prefix="uwbd-demo-") as tmp:
        try:
            return run_demo(Path(tmp), duration_s=args.duration, seed=args.seed, live=live,
                            ros2_router=args.ros2)
        except ZenohStartError as err:
            raise UsageError(f"demo: {err}") from err


def cmd_run(args: argparse.Namespace) -> int:
    """The daemon: serial ports → fusion → MCAP logs, until SIGINT/SIGTERM."""
    config = load_config_file(args.config, warn=True, host=True)
    if not config.sources:
        raise UsageError(f"{args.config}: sources: at least one [[sources]] is needed")
    log_dir = Path(args.log_dir or config.log.get("directory", LOG_DIRECTORY))
    live = foxglove_server(args)
    extra = (live(config),) if live is not None else ()
    try:
        pipeline = asyncio.run(run_daemon(config, log_dir, args.duration, extra_sinks=extra,
                                          summary_s=args.summary_every, where=args.config))
    except PipelineError as err:
        raise RunError(str(err)) from err
    except ZenohStartError as err:
        raise UsageError(f"{args.config}: {err}") from err
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
    zcfg: dict[str, Any] = {"mode": "peer"}
    prefix = args.prefix
    if args.config:
        config = load_config_file(args.config)
        zcfg.update(_daemons_reach(config.zenoh, args.config))
        prefix = prefix or config.zenoh_prefix
    if args.zenoh_config:
        zcfg["config"] = args.zenoh_config
    if args.connect:
        zcfg["connect"] = [*args.connect, *zcfg.get("connect", [])]
    elif not zcfg.get("connect") and "config" not in zcfg:
        zcfg["connect"] = [THIS_HOST_LISTEN]  # a daemon on this host, as it listens by default
    prefix = str(prefix or f"uwbd/{default_robot_name()}")
    if zcfg.get("connect"):
        # it dials a daemon or a router: as a client it needs no listen endpoint of its own,
        # which a peer would (peers mesh with each other directly)
        zcfg["mode"] = "client"
    zcfg["listen"] = []  # never the daemon's own, which its Zenoh file may give
    _zenoh_file_usable(zcfg, "--zenoh-config" if args.zenoh_config else "-c")
    if args.ros2 is not None:
        listen = _ros2_listen(args, config.ros2_settings if args.config else settings_of({}))
    else:
        try:
            zenoh.KeyExpr(f"{prefix.strip('/')}/pose")
        except zenoh.ZError as err:
            raise UsageError(f"--prefix {prefix}: not a key expression ({zenoh_reason(err)}); "
                             "e.g. uwbd/robot1 or uwbd/*") from err
        listen = uwbd_keys(prefix, args.status)
    try:
        printed = echo(zcfg, listen, args.count, args.timeout)
    except EchoError as err:
        raise RunError(str(err)) from err
    if args.timeout is not None and printed == 0:
        raise RunError(f"nothing received on {listen.key} in {args.timeout:g} s")
    return 0


def _ros2_listen(args: argparse.Namespace, settings: Ros2Settings) -> Listen:
    """``--ros2 [TOPIC]``: the topic's key on the settings' domain."""
    if args.status or args.prefix:
        raise UsageError("--ros2 prints a ROS 2 topic: without --status or --prefix (the "
                         "diagnostics are the topic /diagnostics)")
    missing = missing_extra()
    if missing is not None:
        raise UsageError(f"echo --ros2 needs the ros2 extra ({missing} is missing): "
                         f"{EXTRA_HINT}")
    topic = args.ros2 or settings.topics["pose"] or DEFAULT_TOPICS["pose"]
    if not TOPIC_NAME.fullmatch(topic):
        raise UsageError(f"--ros2 {topic}: not a ROS 2 topic name (e.g. /uwbd/pose, /tf)")
    from uwbd.service.ros2_echo import ros2_topic

    return ros2_topic(settings, topic)


def _daemons_reach(zenoh_cfg: dict[str, Any], where: str) -> dict[str, Any]:
    """What a subscriber on the daemon's machine takes from its ``[zenoh]`` table and Zenoh
    file: the daemon's routers and its own listen endpoints to dial (it must not take the
    daemon's listen port itself), its certificates and its scouting."""
    _zenoh_file_usable(dict(zenoh_cfg), f"{where}: zenoh.config")
    daemon = effective(zenoh_cfg)
    out: dict[str, Any] = {"connect": [*daemon["connect"], *dial_endpoints(daemon["listen"])]}
    if "config" in zenoh_cfg:  # the daemon's certificates (and scouting, unless the table's)
        out["config"] = zenoh_cfg["config"]
    if "multicast_scouting" in zenoh_cfg or "config" not in zenoh_cfg:
        out["multicast_scouting"] = zenoh_cfg.get("multicast_scouting", False)
    return out


def _zenoh_file_usable(zcfg: dict[str, Any], option: str) -> None:
    """A Zenoh file given on the command line: checked as ``check-config`` checks one."""
    if "config" in zcfg:
        r = Report(option)
        check_zenoh_file(r, zcfg)
        if r.errors:
            raise UsageError("\n".join(r.errors))


def cmd_router(args: argparse.Namespace) -> int:
    """A Zenoh router for several daemons (as ``zenohd``)."""
    zcfg: dict[str, Any] = {"mode": "router", "multicast_scouting": args.multicast_scouting}
    if args.listen:  # else the Zenoh file's listen endpoints, else the default
        zcfg["listen"] = args.listen
    if args.zenoh_config:
        zcfg["config"] = args.zenoh_config
        _zenoh_file_usable(zcfg, "--zenoh-config")
    try:
        run_router(zcfg, listen_default=[ROUTER_LISTEN_DEFAULT])
    except RouterError as err:
        raise UsageError(str(err)) from err
    return 0


