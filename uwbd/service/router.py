"""``uwbd router``: a Zenoh router for a fleet, where ``zenohd`` is not installed.

Several daemons (each with its own ``[robot] name``, so its own key prefix) connect to one
router, and one subscriber on ``uwbd/*/pose`` there sees every robot. This is a plain
``eclipse-zenoh`` session in router mode: ``zenohd -l tcp/0.0.0.0:7447`` does the same.
"""

from __future__ import annotations

import threading

import zenoh

from uwbd import journal
from uwbd.service.interrupt import wait_until
from uwbd.service.zenohsink import session_config, zenoh_reason

LOG = journal.get("router")


class RouterError(Exception):
    """Zenoh could not start a router with these settings (a port taken, a bad endpoint)."""


def run_router(listen: list[str], multicast_scouting: bool,
               stop: threading.Event | None = None) -> None:
    """Route until Ctrl-C, SIGTERM or ``stop``."""
    try:
        session = zenoh.open(session_config({"mode": "router", "listen": listen,
                                             "multicast_scouting": multicast_scouting}))
    except zenoh.ZError as err:
        raise RouterError(f"cannot start a router on {', '.join(listen)}: "
                          f"{zenoh_reason(err)}") from err
    try:
        LOG.info("routing on %s (multicast scouting %s); daemons connect with [zenoh] "
                 "connect = [%s]", ", ".join(listen), "on" if multicast_scouting else "off",
                 ", ".join(f'"{e}"' for e in listen))
        wait_until(stop or threading.Event())
    finally:
        session.close()
        LOG.info("router stopped")
