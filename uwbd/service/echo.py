"""``uwbd echo``: subscribe to a daemon's poses (or status) and print them, one line each.

Any Zenoh client does the same; from another language, subscribe to ``<prefix>/pose`` and
parse the JSON payload (see the README's "Subscribing from other languages").
"""

from __future__ import annotations

import contextlib
import json
import queue
import time
from typing import Any

import zenoh

from uwbd.service.zenohsink import session_config


def echo(zcfg: dict[str, Any], prefix: str, status: bool, count: int | None,
         timeout_s: float | None) -> int:
    """Print samples until ``count`` were printed, ``timeout_s`` passed, or Ctrl-C.
    Returns how many were printed."""
    key = f"{prefix.strip('/')}/{'status' if status else 'pose'}"
    inbox: queue.Queue[bytes] = queue.Queue(maxsize=1000)

    def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread: hand off, nothing more
        # the printer is behind: dropping beats blocking Zenoh's receive thread
        with contextlib.suppress(queue.Full):
            inbox.put_nowait(sample.payload.to_bytes())

    session = zenoh.open(session_config(zcfg))
    printed = 0
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        subscriber = session.declare_subscriber(key, on_sample)
        if status:  # the current status right away, from the queryable
            for reply in session.get(key, timeout=2.0):
                if reply.ok is not None:
                    inbox.put_nowait(reply.ok.payload.to_bytes())
        while count is None or printed < count:
            wait = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if wait <= 0:
                break
            try:
                payload = inbox.get(timeout=wait)
            except queue.Empty:
                continue
            print(_line(json.loads(payload), status), flush=True)
            printed += 1
        subscriber.undeclare()
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return printed


def _line(msg: dict[str, Any], status: bool) -> str:
    if status:
        return json.dumps(msg)
    p, q = msg["pose"]["position"], msg["pose"]["orientation"]
    return (f"{msg['t_ns']}  p=({p['x']:.3f}, {p['y']:.3f}, {p['z']:.3f}) m  "
            f"q=({q['x']:.3f}, {q['y']:.3f}, {q['z']:.3f}, {q['w']:.3f})  {msg.get('status', '')}")
