"""``uwbd router``: a Zenoh router for a fleet, where ``zenohd`` is not installed.

Several daemons (each with its own ``[robot] name``, so its own key prefix) connect to one
router, and one subscriber on ``uwbd/*/pose`` there sees every robot. This is a plain
``eclipse-zenoh`` session in router mode: ``zenohd -l tcp/0.0.0.0:7447`` does the same.
"""

from __future__ import annotations

import json
import socket
import threading
from typing import Any

import zenoh

from uwbd import journal
from uwbd.config.zenoh_checks import plaintext_beyond_this_host
from uwbd.config.zenoh_session import endpoints, session_config, zenoh_reason
from uwbd.service.interrupt import wait_until

LOG = journal.get("router")


class RouterError(Exception):
    """Zenoh could not start a router with these settings (a port taken, a bad endpoint)."""


def run_router(zcfg: dict[str, Any], stop: threading.Event | None = None,
               listen_default: list[str] | None = None) -> None:
    """Route until Ctrl-C, SIGTERM or ``stop``; ``zcfg`` as a ``[zenoh]`` table (mode
    router, listen, multicast_scouting, a Zenoh file in ``config``); ``listen_default``
    where neither it nor the file gives a listen endpoint."""
    try:
        config = session_config(zcfg, {"mode": "router", "listen": listen_default or []})
        session = zenoh.open(config)
    except zenoh.ZError as err:
        where = ", ".join(zcfg.get("listen", listen_default or [])) or zcfg.get("config", "")
        raise RouterError(f"cannot start a router on {where}: {zenoh_reason(err)}") from err
    listen = endpoints(config, "listen", "router")
    open_to_all = [e for e in listen if plaintext_beyond_this_host(e)]
    if open_to_all and "config" not in zcfg:
        LOG.warning("%s is reachable from the network without encryption or authentication: "
                    "anyone there can read every robot's poses and publish false ones. Secure "
                    "it with TLS and access control (--zenoh-config with the shipped "
                    "config/zenoh/router.json5, docs/security.md), or listen on "
                    "127.0.0.1 (--listen tcp/127.0.0.1:7447)", ", ".join(open_to_all))
    try:
        LOG.info("routing on %s (multicast scouting %s); daemons connect with [zenoh] "
                 "connect = [%s]", ", ".join(listen),
                 "on" if json.loads(config.get_json("scouting/multicast/enabled")) else "off",
                 ", ".join(f'"{_dialled(e)}"' for e in listen))
        wait_until(stop or threading.Event())
    except KeyboardInterrupt:
        pass  # Ctrl-C as it started: a stop all the same
    finally:
        session.close()
        LOG.info("router stopped")


def _dialled(endpoint: str) -> str:
    """What a daemon on another machine dials for a listen endpoint: this machine's name in
    place of a wildcard address."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if host in ("0.0.0.0", "[::]"):
        host = socket.gethostname()
    return f"{proto}/{host}:{port}" if port else endpoint
