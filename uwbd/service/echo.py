"""``uwbd echo``: subscribe to a daemon's poses (or status) and print them, one line each.

It dials where the daemon can be reached: ``--connect`` endpoints, or, with ``-c``, the
config's ``connect`` endpoints and its ``listen`` endpoints turned into addresses to dial
(``tcp/0.0.0.0:7447`` → ``tcp/127.0.0.1:7447``). When nothing arrives for a few seconds it
says so, with the daemons it does see (their liveliness tokens ``<prefix>/alive``). With a
wildcard in the prefix (``uwbd/*``) every line starts with the key it came on, so the
robots can be told apart.

Any Zenoh client does the same; from another language, subscribe to ``<prefix>/pose`` and
parse the JSON payload (docs/fleet.md, "Subscribing").
"""

from __future__ import annotations

import contextlib
import json
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

from uwbd import journal
from uwbd.config.zenoh_session import session_config, zenoh_reason

LOG = journal.get("echo")
QUIET_AFTER_S = 3.0  # nothing this long: say what is (not) there


class EchoError(Exception):
    """Nothing could be reached where the daemon was said to be."""


def dial_endpoints(listen: list[str]) -> list[str]:
    """The addresses a client dials to reach a process listening on ``listen``."""
    out = []
    for endpoint in listen:
        proto, _, address = endpoint.partition("/")
        address = (address.replace("0.0.0.0:", "127.0.0.1:", 1)
                   .replace("[::]:", "[::1]:", 1))
        out.append(f"{proto}/{address}")
    return out


@dataclass(frozen=True)
class Listen:
    """What to print: the key to subscribe to, a line per sample (its key, payload and
    attachment), what to say when nothing arrives (the session, how it was reached), and
    whether to ask the key's queryable first, or the publishers' caches."""

    key: str
    line: Callable[[str, bytes, bytes | None], str]
    quiet: Callable[[zenoh.Session, str], None]
    query_first: bool = False
    history: bool = False  # also what publishers with a cache hold (a latched /tf_static)


def uwbd_keys(prefix: str, status: bool) -> Listen:
    """uwbd's own JSON keys: ``<prefix>/pose`` or ``<prefix>/status``."""
    key = f"{prefix.strip('/')}/{'status' if status else 'pose'}"
    show_key = "*" in key

    def line(sample_key: str, payload: bytes, _attachment: bytes | None) -> str:
        text = _line(payload, status)
        return f"{sample_key}  {text}" if show_key else text
    return Listen(key, line, lambda session, where: _say_what_is_there(session, key, where),
                  query_first=status)


def echo(zcfg: dict[str, Any], listen: Listen, count: int | None,
         timeout_s: float | None) -> int:
    """Print samples until ``count`` were printed, ``timeout_s`` passed, or Ctrl-C.
    Returns how many were printed."""
    key = listen.key
    inbox: queue.Queue[tuple[str, bytes, bytes | None]] = queue.Queue(maxsize=1000)

    def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread: hand off, nothing more
        attachment = None if sample.attachment is None else sample.attachment.to_bytes()
        # the printer is behind: dropping beats blocking Zenoh's receive thread
        with contextlib.suppress(queue.Full):
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), attachment))

    where = ", ".join(zcfg.get("connect", [])) or "peers found by multicast scouting"
    try:
        session = zenoh.open(session_config(zcfg))
    except zenoh.ZError as err:
        raise EchoError(f"cannot reach {where}: {zenoh_reason(err)}; is the daemon (uwbd run) "
                        "or the router running there?") from err
    LOG.info("listening on %s (via %s)", key, where)
    printed = 0
    started = last = time.monotonic()
    deadline = None if timeout_s is None else started + timeout_s
    said_quiet = False
    try:
        subscriber: Any
        if listen.history:  # as a transient-local ROS 2 subscription (rmw_zenoh)
            subscriber = zenoh.ext.declare_advanced_subscriber(
                session, key, on_sample, subscriber_detection=True,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1))
        else:
            subscriber = session.declare_subscriber(key, on_sample)
        if listen.query_first:  # the current status right away, from the queryable
            for reply in session.get(key, timeout=2.0):
                if reply.ok is not None:
                    inbox.put_nowait((str(reply.ok.key_expr), reply.ok.payload.to_bytes(), None))
        while count is None or printed < count:
            wait = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if wait <= 0:
                break
            try:
                sample_key, payload, attachment = inbox.get(timeout=wait)
            except queue.Empty:
                if not said_quiet and time.monotonic() - last >= QUIET_AFTER_S:
                    said_quiet = True
                    listen.quiet(session, where)
                continue
            last = time.monotonic()
            if said_quiet:
                said_quiet = False
                LOG.info("receiving on %s", sample_key)
            print(listen.line(sample_key, payload, attachment), flush=True)
            printed += 1
        subscriber.undeclare()
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return printed


def _say_what_is_there(session: zenoh.Session, key: str, where: str) -> None:
    """Nothing arrives on ``key``: list the daemons whose liveliness tokens are visible."""
    alive = sorted({str(r.ok.key_expr).removesuffix("/alive")
                    for r in session.liveliness().get("**/alive", timeout=1.0)
                    if r.ok is not None})
    if alive:
        LOG.warning("nothing published on %s for %.0f s; daemons seen: %s (pick one with "
                    "--prefix)", key, QUIET_AFTER_S, ", ".join(alive))
    else:
        LOG.warning("nothing published on %s for %.0f s, and no uwbd daemon seen via %s: is "
                    "it running, and can it be reached there (-c CONFIG or --connect "
                    "ENDPOINT)?", key, QUIET_AFTER_S, where)


def _line(payload: bytes, status: bool) -> str:
    try:
        msg = json.loads(payload)
        if status:
            return json.dumps(msg)
        p, q = msg["pose"]["position"], msg["pose"]["orientation"]
        health = msg.get("health") or {}
        hpl, vpl = health.get("horizontal_protection_m"), health.get("vertical_protection_m")
        bound = "" if hpl is None or vpl is None else f"  ±{hpl:.2f} h ±{vpl:.2f} v m"
        return (f"{msg['t_ns']}  p=({p['x']:.3f}, {p['y']:.3f}, {p['z']:.3f}) m  "
                f"q=({q['x']:.3f}, {q['y']:.3f}, {q['z']:.3f}, {q['w']:.3f}){bound}  "
                f"{msg.get('status', '')}")
    except (ValueError, KeyError, TypeError) as err:
        return f"(not a uwbd pose: {type(err).__name__}: {payload[:80]!r})"
