"""``uwbd replay``: a log's reads through the same pipeline as the live daemon.

The ``/raw/<source>`` messages go to :meth:`Pipeline.on_bytes` in log order with their
logged receive times, so the poses equal those the live run computed, bit for bit. A log
with no raw channels (an imported dataset) replays its decoded ``/imu`` and ``/uwb`` frames.
The output log (``-o``) also gets the source's ``/truth``, so it can be scored in turn.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import orjson

from uwbd import journal
from uwbd.codec import frame_from_dict
from uwbd.config import parse
from uwbd.logs.reading import LogContents, LogMessage
from uwbd.logs.sink import McapSink
from uwbd.service.pipeline import Pipeline, PoseList, Sink, monotonic_pacer

RAW_PREFIX = "/raw/"
LOG = journal.get("replay")


def replay(contents: LogContents, where: str, output: Path | None = None,
           realtime: bool = False, progress: bool = False,
           config_toml: str | None = None) -> tuple[Pipeline, PoseList]:
    """Replay with the log's own config, or ``config_toml`` (what ``-c``/``--set`` make);
    the output log records the config used."""
    config = (parse(contents.metadata.get("config_toml", ""), f"{where} (metadata)")
              if config_toml is None else parse(config_toml, f"{where} (with -c/--set)"))
    poses = PoseList()
    sinks: list[Sink] = [poses]
    out = None if output is None else McapSink(config, path=output)
    if out is not None:
        sinks.append(out)
    pipeline = Pipeline(config, sinks)
    raw = [m for m in contents.messages if m.topic.startswith(RAW_PREFIX)]
    items = raw or [m for m in contents.messages if m.topic in ("/imu", "/uwb")]
    truth = [m for m in contents.messages if m.topic == "/truth"] if out is not None else []
    pace = monotonic_pacer(items[0].log_time_ns) if realtime and items else None
    try:
        for m in _progress(heapq.merge(items, truth, key=lambda m: m.log_time_ns)
                           if truth else items, len(items) + len(truth), progress):
            if m.topic == "/truth":
                assert out is not None
                record = _json_record(m.data)
                if record is None:
                    pipeline.bad_records += 1  # a damaged record: counted, the rest go on
                    if pipeline.bad_records == 1:
                        LOG.warning("%s: a /truth record at %d ns is not JSON; skipped", where,
                                    m.log_time_ns)
                    continue
                out.json("/truth", m.log_time_ns, record, "foxglove.PoseInFrame")
                continue
            if pace is not None:
                pace(m.log_time_ns)
            if raw:
                pipeline.on_bytes(m.topic[len(RAW_PREFIX):], m.log_time_ns, m.data)
                continue
            try:
                frame = frame_from_dict(json.loads(m.data))
            except (ValueError, KeyError, TypeError, IndexError) as err:
                pipeline.bad_records += 1  # a damaged record: counted, the rest go on
                if pipeline.bad_records == 1:
                    LOG.warning("%s: a %s record at %d ns is not a frame (%s: %s); skipped",
                                where, m.topic, m.log_time_ns, type(err).__name__, err)
                continue
            pipeline.on_frame(frame)
        pipeline.finish()
    finally:  # an interrupted replay (Ctrl-C under --realtime) still finishes -o
        pipeline.close()
    return pipeline, poses


def _progress(items: Iterable[LogMessage], total: int, shown: bool) -> Iterable[LogMessage]:
    """``items``, with a progress bar on stderr when ``shown`` (tqdm is imported then)."""
    if not shown:
        return items
    from tqdm import tqdm  # noqa: PLC0415 - only for a progress bar

    bar: Iterable[LogMessage] = tqdm(items, total=total, desc="replay", unit="read",
                                     leave=False, mininterval=0.5)
    return bar


def _json_record(data: bytes) -> dict[str, Any] | None:
    """A JSON object record (orjson; the json module for what orjson refuses, such as
    ``NaN`` in logs written before every record was strict), ``None`` if it is none."""
    try:
        obj = orjson.loads(data)
    except orjson.JSONDecodeError:
        try:
            obj = json.loads(data)
        except ValueError:
            return None
    return obj if isinstance(obj, dict) else None
