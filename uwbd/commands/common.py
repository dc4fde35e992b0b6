"""What the commands share: their two errors (a usage problem, exit 2; a failure while
working, exit 1) and the checks of what they are given (files, folders, drivers, configs,
logs, extras)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers import PARSERS
from uwbd import journal
from uwbd.codec import frame_from_dict
from uwbd.config import Config, ConfigError, apply_overrides
from uwbd.config import load as load_config
from uwbd.config import parse as parse_config
from uwbd.config.zenoh_checks import host_problems
from uwbd.logs.reading import LogContents, not_a_log, read_log

LOG = journal.get("cli")
SAMPLED_RECORDS = 50  # decoded records tried before a log is said to hold no frames


class UsageError(Exception):
    """A problem with what the user asked for; printed as one line, exit code 2."""


class RunError(Exception):
    """The command failed while working (an output it could not write); exit code 1."""


def writable_folder(target: Path, what: str) -> None:
    """Fail before any work when ``target`` (a file to write) cannot be created, or is there
    and is not a regular file (a device node, a FIFO, a socket, a folder): a command writes
    and removes nothing but regular files of its own."""
    folder = target.parent
    if not folder.is_dir():
        raise UsageError(f"cannot write {what} {target}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"cannot write {what} {target}: folder {folder} is not writable")
    try:
        mode = target.stat().st_mode
    except FileNotFoundError:
        return
    except OSError as err:
        raise UsageError(f"cannot write {what} {target}: {err.strerror or err}") from err
    if not stat.S_ISREG(mode):
        kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                else "a socket" if stat.S_ISSOCK(mode) else "a device node")
        raise UsageError(f"cannot write {what} {target}: it is {kind}, not a file; give the "
                         "path of a file to write")


@contextlib.contextmanager
def written(target: Path, what: str) -> Iterator[Path]:
    """A new file beside ``target`` to write in the block: renamed over ``target`` when the
    block ends well, removed when it does not (``target`` is then as it was). Checked first
    as :func:`writable_folder` checks."""
    writable_folder(target, what)
    final = target.resolve() if target.is_symlink() else target  # the file a link names
    while True:
        tmp = final.with_name(f".{final.name}.{secrets.token_hex(4)}.part")
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            break
        except FileExistsError:
            continue
        except OSError as err:
            raise RunError(f"cannot write {target}: {err.strerror or err}") from err
    try:
        yield tmp
        os.replace(tmp, final)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise RunError(f"cannot write {target}: {err.strerror or err}") from err
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def driver_name(name: str) -> str:
    if name not in PARSERS:
        raise UsageError(f"unknown driver {name!r} (known: {', '.join(PARSERS)})")
    return name


FOXGLOVE_DEFAULT = "127.0.0.1:8765"
ROUTER_LISTEN_DEFAULT = "tcp/0.0.0.0:7447"  # `uwbd router` without --listen
# where a ROS 2 node running rmw_zenoh finds its router (rmw_zenohd) by default
ROS2_ROUTER_DEFAULT = "tcp/127.0.0.1:7447"


def foxglove_server(args: argparse.Namespace) -> Callable[[Config], Any] | None:
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


def open_log(name: str, doing: str) -> tuple[Path, LogContents]:
    """A log read for ``doing``; of a log cut short by a crash or damaged, what is intact
    (every chunk that reads whole) is used, and a warning says what was not."""
    path = Path(name)
    if not path.exists():
        raise UsageError(f"cannot read {path}: no such file")
    problem = not_a_log(path)
    if problem:
        raise UsageError(problem)
    contents = read_log(path)
    if contents.truncated:
        LOG.warning("%s; %s what is intact", contents.error, doing)
    return path, contents


def log_config(args: argparse.Namespace, path: Path, contents: LogContents) -> str | None:
    """The config to run a log with: the log's own, or ``-c``'s, with the ``--set`` items;
    ``None`` for the log's own unchanged."""
    if args.config:
        text = read_config_text(Path(args.config))
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


def read_config_text(path: Path) -> str:
    try:
        return load_config(path).text
    except ConfigError as err:
        raise UsageError(str(err)) from err


def require_matching_sources(path: Path, contents: LogContents, config: Config,
                             config_name: str) -> None:
    """A log's raw reads run only through sources of the same name: a config naming none of
    them would replay nothing, and say nothing of why."""
    logged = sorted({m.topic[5:] for m in contents.messages if m.topic.startswith("/raw/")})
    names = [s.name for s in config.sources]
    if logged and not set(logged) & set(names):
        raise UsageError(
            f"{config_name}: its sources ({', '.join(names) or 'none'}) name none of the "
            f"log's ({', '.join(logged)}): name the [[sources]] as the log does, or leave out "
            f"-c to run {path} with the config it was recorded with")


def require_replayable(path: Path, contents: LogContents) -> None:
    """Something to run: raw reads, or decoded frames of which some decode (a foreign log
    with channels of uwbd's names, holding something else, is said to be one)."""
    if any(m.topic.startswith("/raw/") for m in contents.messages):
        return
    decoded = [m for m in contents.messages if m.topic in ("/imu", "/uwb")]
    if not decoded:
        raise UsageError(f"{path}: nothing to run (no /raw/*, /imu or /uwb messages; topics: "
                         f"{', '.join(sorted(contents.topics())) or 'none'})")
    problem = ""
    for m in decoded[:SAMPLED_RECORDS]:
        try:
            frame_from_dict(json.loads(m.data))
        except (ValueError, KeyError, TypeError, IndexError) as err:
            problem = problem or f"the first, at {m.log_time_ns} ns: {err}"
        else:
            return
    raise UsageError(f"{path}: its /imu and /uwb records are not uwbd's frames (none of the "
                     f"first {min(len(decoded), SAMPLED_RECORDS)} decodes; {problem}): is it "
                     "another program's log?")


def tools_report(command: str) -> Any:
    """The report function, from the ``tools`` extra (matplotlib, scipy, filterpy), which the
    robot's install leaves out; imported here so it never sits in the daemon's memory."""
    try:
        from uwbd.tools.report import report
    except ImportError as err:
        raise UsageError(f"{command} needs the tools extra ({err.name} is missing): "
                         "pip install 'uwbd[tools]' (from a checkout: pip install '.[tools]')"
                         ) from err
    return report


def write_atomically(target: Path, text: str, what: str = "the file") -> None:
    """``text`` into ``target`` whole or not at all (a new file renamed over it)."""
    with written(target, what) as tmp:
        tmp.write_text(text, encoding="utf-8")


def load_config_file(path: str, warn: bool = False, host: bool = False) -> Config:
    """A configuration file, or every problem with it, one line each naming file and key
    (exit 2); ``warn``: the warnings of a config that loads are said too; ``host``: what
    this machine needs to run it is checked too (the Zenoh file and its certificates)."""
    try:
        config = load_config(Path(path))
    except ConfigError as err:
        raise UsageError(str(err)) from err
    checked = host_problems(config, path) if host else None
    if checked is not None and checked.errors:
        raise UsageError("\n".join(checked.errors))
    if warn:
        for warning in [*config.warnings, *(checked.warnings if checked else [])]:
            LOG.warning("%s", warning)
    return config


@dataclass(frozen=True)
class ConfigRewrite:
    """``--write-config BASE OUT``: the base config (it loads as it is) and where its copy
    with the found keys goes."""

    base: Path
    text: str
    out: Path

    @staticmethod
    def of(args: argparse.Namespace, *others: Path) -> ConfigRewrite | None:
        """Checked before any work: ``OUT`` writable, and neither the base nor ``others``
        (the log)."""
        if not args.write_config:
            return None
        base, out = Path(args.write_config[0]), Path(args.write_config[1])
        text = read_config_text(base)
        if out.exists():
            for other, what in ((base, "config"), *((o, "log") for o in others)):
                if out.resolve() == other.resolve():
                    raise UsageError(f"{out}: give another file to write, not the {what} "
                                     "itself")
        writable_folder(out, "the config")
        return ConfigRewrite(base, text, out)

    def write(self, overrides: list[str], said: str) -> None:
        """The base with ``overrides`` set, checked as a config, written whole."""
        try:
            new = apply_overrides(self.text, overrides, str(self.base))
            parse_config(new, str(self.out))
        except ConfigError as err:
            raise UsageError(str(err)) from err
        write_atomically(self.out, new)
        print(f"wrote {self.out}: {self.base} with {said}")
