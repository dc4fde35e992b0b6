"""The Zenoh session a ``[zenoh]`` table asks for (the daemon's, ``echo``'s, ``router``'s),
and Zenoh's errors as a user reads them."""

from __future__ import annotations

import json
import re
from typing import Any

import zenoh


def zenoh_reason(err: Exception) -> str:
    """A Zenoh error as a user reads it, on one line: without the Rust source location it
    ends with."""
    return " ".join(re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(err)).split())


# [zenoh] key -> where it goes in a Zenoh config
ZENOH_PATHS = {"mode": "mode", "connect": "connect/endpoints", "listen": "listen/endpoints",
               "multicast_scouting": "scouting/multicast/enabled"}


# where a daemon with no [zenoh] table, or one that gives no endpoint, listens: this host only
# (``uwbd echo`` dials it there)
THIS_HOST_LISTEN = "tcp/127.0.0.1:7447"
# what uwbd sets where neither the table nor a Zenoh file does: this host only (Zenoh's own
# defaults differ: a peer listens on every interface, tcp/[::]:0, and scouts the LAN)
UWBD_DEFAULTS: dict[str, Any] = {"mode": "peer", "connect": [], "listen": [],
                                 "multicast_scouting": False}


def session_config(zcfg: dict[str, Any],
                   defaults: dict[str, Any] | None = None) -> zenoh.Config:
    """A Zenoh config from the ``[zenoh]`` table (mode, connect, listen, multicast_scouting).
    With ``config``, a Zenoh config file (JSON5: TLS, authentication, access control, all
    Zenoh's own) is the base, and the keys the table gives are set over it. A key neither
    gives is ``defaults``' (uwbd's: a peer, not scouting, listening on this host only where
    no endpoint is given at all), never Zenoh's own default."""
    path = zcfg.get("config")
    config: zenoh.Config = (zenoh.Config() if path is None
                            else zenoh.Config.from_file(str(path)))
    untouched = zenoh.Config()
    alone = not any(key in zcfg or config.get_json(ZENOH_PATHS[key])
                    != untouched.get_json(ZENOH_PATHS[key]) for key in ("connect", "listen"))
    defaults = {**UWBD_DEFAULTS, **({"listen": [THIS_HOST_LISTEN]} if alone else {}),
                **(defaults or {})}
    for key, where in ZENOH_PATHS.items():
        if key in zcfg:
            value = zcfg[key]
        elif config.get_json(where) == untouched.get_json(where):  # the file left it
            value = defaults[key]
        else:
            continue
        config.insert_json5(where, json.dumps(value))
    return config


def endpoints(config: zenoh.Config, section: str, mode: str | None = None) -> list[str]:
    """The ``listen`` or ``connect`` endpoints of a Zenoh config (of ``mode``'s, where they
    are given per mode; every mode's without one)."""
    try:
        listed = json.loads(config.get_json(f"{section}/endpoints")) or []
    except (zenoh.ZError, ValueError):
        return []
    if isinstance(listed, dict):  # per mode: {router: [...], peer: [...]}
        chosen = [listed.get(mode)] if mode else list(listed.values())
        listed = [e for v in chosen for e in (v or [])]
    return [e for e in listed if isinstance(e, str)]


def effective(zcfg: dict[str, Any]) -> dict[str, Any]:
    """The four keys of ``ZENOH_PATHS`` as the session will have them (the table over its
    Zenoh file over uwbd's defaults); the table's own where the file cannot be read."""
    try:
        config = session_config(zcfg)
        mode = json.loads(config.get_json("mode"))
        return {"mode": mode, "connect": endpoints(config, "connect", mode),
                "listen": endpoints(config, "listen", mode),
                "multicast_scouting": bool(json.loads(
                    config.get_json("scouting/multicast/enabled")))}
    except (zenoh.ZError, ValueError):
        return {**UWBD_DEFAULTS, **{k: zcfg[k] for k in ZENOH_PATHS if k in zcfg}}
