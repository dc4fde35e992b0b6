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


def session_config(zcfg: dict[str, Any]) -> zenoh.Config:
    """A Zenoh config from the ``[zenoh]`` table (mode, connect, listen, multicast_scouting).
    With ``config``, a Zenoh config file (JSON5: TLS, authentication, access control, all
    Zenoh's own) is the base, and only the keys the table gives are set over it."""
    path = zcfg.get("config")
    if path is None:
        config: zenoh.Config = zenoh.Config.from_json5(json.dumps({
            "mode": zcfg.get("mode", "peer"),
            "connect": {"endpoints": list(zcfg.get("connect", []))},
            "listen": {"endpoints": list(zcfg.get("listen", []))},
            "scouting": {"multicast": {"enabled": bool(zcfg.get("multicast_scouting", True))}},
        }))
        return config
    config = zenoh.Config.from_file(str(path))
    for key, where in ZENOH_PATHS.items():
        if key in zcfg:
            config.insert_json5(where, json.dumps(zcfg[key]))
    return config
