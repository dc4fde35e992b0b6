"""The configuration's command: ``check-config``."""

from __future__ import annotations

import argparse
from pathlib import Path

from uwbd.commands.common import LOG, UsageError
from uwbd.config import ConfigError
from uwbd.config import load as load_config
from uwbd.config.zenoh_checks import host_problems


def cmd_check_config(args: argparse.Namespace) -> int:
    """Validate a configuration file: its warnings, then every problem (exit 2) or one line
    saying it is fine."""
    try:
        config = load_config(Path(args.config))
    except ConfigError as err:
        for warning in err.warnings:
            LOG.warning("%s", warning)
        raise UsageError(str(err)) from err
    host = host_problems(config, args.config)
    warnings = [*config.warnings, *host.warnings]
    for warning in warnings:
        LOG.warning("%s", warning)
    if host.errors:
        raise UsageError("\n".join(host.errors))
    ports = ", ".join(f"{s.name}={s.driver}@{s.port}" for s in config.sources) or "no sources"
    what = f"{config.filter_config().mode.value} fusion"
    ros2 = config.ros2_settings
    if ros2.enabled:
        what += f"; ROS 2 topics on domain {ros2.domain_id} ({ros2.domain_from})"
    print(f"{args.config}: ok ({ports}; {len(config.anchors_m)} anchors; {what}"
          + (f"; {len(warnings)} warning(s) above)" if warnings else ")"))
    return 0
