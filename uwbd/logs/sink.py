"""The log sink: the pipeline's records into MCAP files, written behind, rotated, flushed."""

from __future__ import annotations

import contextlib
import errno
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from drivers import Frame
from uwbd import journal
from uwbd.config import Config
from uwbd.fusion.types import Pose
from uwbd.logs.foxglove import FoxgloveView
from uwbd.logs.mcaplog import UNENCODABLE, LogWriter, SourceInfo, finish_cut, pose_json

FLUSH_PERIOD_NS = 1_000_000_000  # the log is handed to the OS about once a second
WRITE_BEHIND_NS = 100_000_000  # records wait this long in memory, then are written together
MAX_BEHIND_NS = 500_000_000  # the longest they wait when the owner paces the writing
RETRY_NS = 5_000_000_000  # after a failure, a new log file is tried this often
LOG = journal.get("log")


class McapSink:
    """Writes the pipeline to MCAP files: one file, or a rotating series in a directory.

    In a directory, files are named ``uwbd-<robot>-<UTC start, %Y%m%d-%H%M%S>.mcap``, so
    the logs of several robots can share a folder. Rotation starts a new file when the
    current one passes ``rotate_bytes`` or spans
    ``rotate_ns`` of data time. Records are written behind: kept until they span
    ``WRITE_BEHIND_NS`` and then written in one go, on warm caches (one by one, each record
    cost the daemon twice the CPU). With ``paced`` the owner calls :meth:`write_pending`
    when it has time (the daemon: on a read that brings no pose, so the writing never
    delays one); records then wait at most ``MAX_BEHIND_NS``. The file is flushed about
    once a second of data time, so a crash loses about 1.1 s (1.5 s at worst).

    Every file gets the viewer channels of :mod:`uwbd.logs.foxglove` (``/tf``, ``/anchors``,
    ``/trajectory``) from one :class:`FoxgloveView`, so a rotated file shows the anchors
    and the trajectory goes on across files.

    An ``OSError`` (disk full, directory gone) never reaches the pipeline: logging pauses,
    the reason is in :attr:`error` (the status) and in a warning line, and the file it cut
    is finished in place with what was flushed (:func:`finish_cut`). In a directory, a new
    file is tried every ``RETRY_NS`` of data time, so logging resumes by itself once there is
    room again; records in between are counted in :attr:`records_lost`. A record that
    cannot be encoded is counted (:attr:`bad_records`) and skipped; the rest go on.
    """

    def __init__(self, config: Config, path: Path | None = None, directory: Path | None = None,
                 rotate_bytes: int | None = None, rotate_ns: int | None = None,
                 paced: bool = False) -> None:
        if (path is None) == (directory is None):
            raise ValueError("give either a file path or a directory")
        self.config = config
        self.path = path
        self.directory = directory
        self.rotate_bytes = rotate_bytes
        self.rotate_ns = rotate_ns
        self.files: list[Path] = []
        self.error = ""
        self.records_lost = 0  # while logging was paused
        self.bad_records = 0  # could not be encoded
        self._retry_ns: int | None = None  # data time of the next try after a failure
        self._log: LogWriter | None = None
        self._opened_ns = 0
        self._flushed_ns = 0
        self._behind: list[tuple[int, Callable[..., None], tuple[Any, ...]]] = []
        self._max_behind_ns = MAX_BEHIND_NS if paced else WRITE_BEHIND_NS
        self.view = FoxgloveView.from_config(config)

    def _paused(self, t_ns: int) -> bool:
        """Logging has stopped and no new file is to be tried yet."""
        return bool(self.error) and self._log is None and (
            self._retry_ns is None or t_ns < self._retry_ns)

    def _writer(self, t_ns: int) -> LogWriter | None:
        if self._paused(t_ns):
            return None
        log = self._log
        # rotation is judged at flush time (about once a second), not on every message
        if log is not None and self.directory is not None and self._due_flush(t_ns):
            try:
                full = (self.rotate_bytes is not None
                        and log.path.stat().st_size >= self.rotate_bytes)
            except OSError as err:  # the file or its folder was removed under us
                self._fail(f"{log.path}: {err.strerror or err}", t_ns)
                return None
            if full or (self.rotate_ns and t_ns - self._opened_ns >= self.rotate_ns):
                self._close_current()
                log = None
        if log is None:
            if self.error:
                self._retry_ns = t_ns + RETRY_NS  # should this try fail too
            path = self.path or self._next_name(t_ns)
            sources = tuple(SourceInfo(s.name, s.driver, s.port) for s in self.config.sources)
            try:
                if self.directory is not None:
                    self.directory.mkdir(parents=True, exist_ok=True)
                for _ in range(100):
                    try:  # in a folder, a file another process made meanwhile is kept
                        log = self._log = LogWriter(
                            path, self.config.text, sources, robot=self.config.robot_name,
                            view=self.view, exclusive=self.directory is not None)
                        break
                    except FileExistsError:
                        path = self._next_name(t_ns)
                else:
                    raise FileExistsError(errno.EEXIST, "100 names taken", str(path))
            except FileExistsError as err:
                self._fail(f"cannot write log {path}: {err.strerror or err}", t_ns)
                return None
            except OSError as err:
                with contextlib.suppress(OSError):
                    path.unlink(missing_ok=True)  # half a header is no log
                self._fail(f"cannot write log {path}: {err.strerror or err}", t_ns)
                return None
            self.files.append(path)
            self._opened_ns = self._flushed_ns = t_ns
            LOG.debug("logging to %s", path)
        return log

    def _flushed(self, log: LogWriter) -> None:
        """A flush went through: a log that was paused has resumed (said only now, once
        data reached the disk)."""
        if self.error:
            LOG.info("logging resumed into %s (%d records lost while it was stopped)",
                     log.path, self.records_lost)
            self.error = ""
            self._retry_ns = None

    def _due_flush(self, t_ns: int) -> bool:
        return t_ns - self._flushed_ns >= FLUSH_PERIOD_NS

    def _next_name(self, t_ns: int) -> Path:
        assert self.directory is not None
        stamp = datetime.fromtimestamp(t_ns / 1e9, tz=timezone.utc).strftime("%Y%m%d-%H%M%S")
        name = f"uwbd-{self.config.robot_name}-{stamp}"
        path = self.directory / f"{name}.mcap"
        k = 1
        while path.exists() or path in self.files:
            path = self.directory / f"{name}-{k}.mcap"
            k += 1
        return path

    def _write(self, t_ns: int, action: Callable[..., None], *args: Any) -> None:
        """``action`` (a :class:`LogWriter` method) with ``args``, written behind."""
        if self.error and self._paused(t_ns):
            # logging has stopped: keep nothing until the next try
            self.records_lost += self._records(action, args)
            return
        behind = self._behind
        behind.append((t_ns, action, args))
        if t_ns - behind[0][0] >= self._max_behind_ns:
            self.write_pending(everything=True)

    def _records(self, action: Callable[..., None], args: tuple[Any, ...]) -> int:
        """How many records ``action`` would have written: a pose writes ``/pose`` and
        ``/tf``, and ``/trajectory`` when one is due (the trail moves on as if written)."""
        if action is LogWriter.pose:
            return 2 + (self.view.trajectory(args[0]) is not None)
        return 1

    def write_pending(self, everything: bool = False) -> None:
        """Write the records kept back once they span ``WRITE_BEHIND_NS`` of data time (or
        ``everything`` now)."""
        behind = self._behind
        if not behind or (not everything and behind[-1][0] - behind[0][0] < WRITE_BEHIND_NS):
            return
        self._behind = []
        log = None
        for t_ns, action, args in behind:
            # the writer (and with it rotation) is looked at again only when a flush is due
            due = t_ns - self._flushed_ns >= FLUSH_PERIOD_NS
            if log is None or due:
                log = self._writer(t_ns)
                if log is None:
                    self.records_lost += self._records(action, args)
                    continue
                due = t_ns - self._flushed_ns >= FLUSH_PERIOD_NS  # a new file: not yet
            before = log.unflushed
            try:
                action(log, *args)
                if due:
                    log.flush()
                    self._flushed_ns = t_ns
                    self._flushed(log)
            except OSError as err:
                # the cut counts the records tried (unflushed); a pose's later ones were not
                tried = log.unflushed - before
                self._fail(f"writing {log.path}: {err.strerror or err}", t_ns)
                if action is LogWriter.pose and tried < 3:  # its trajectory not yet judged
                    self.records_lost += max(self._records(action, args) - tried, 0)
                log = None
            except UNENCODABLE as err:  # a record that cannot be encoded
                first = not self.bad_records
                self.bad_records += getattr(err, "records", 1)
                if first:
                    LOG.warning("a %s record could not be written to %s (%s); it is skipped",
                                action.__name__, log.path, err)

    def _fail(self, reason: str, t_ns: int) -> None:
        """Logging pauses: the cut file is finished with what reached it; a directory sink
        tries a new file in ``RETRY_NS``."""
        first = not self.error
        self.error = f"logging stopped: {reason}"
        log, self._log = self._log, None
        if log is not None:
            self.records_lost += log.unflushed  # the cut loses them (the failing one among)
            log.abandon()
            try:
                if log.flushed_bytes <= log.header_bytes:  # no message reached it: no log
                    log.path.unlink()
                    self.files.remove(log.path)
                    kept = f"{log.path} held no message and is removed"
                else:
                    finish_cut(log.path, log.flushed_bytes)
                    kept = f"{log.path} is finished with what was written before"
            except OSError as err:
                kept = (f"{log.path} could not be finished ({err.strerror or err}); "
                        f"`uwbd recover {log.path} -o OUT` reads what it holds")
        else:
            kept = "no file was open"
        self._retry_ns = t_ns + RETRY_NS if self.directory is not None else None
        if first:
            LOG.warning("%s; %s; %s", self.error, kept,
                        "a new file is tried every 5 s" if self.directory is not None
                        else "nothing more is written")

    def raw(self, source: str, t_ns: int, data: bytes) -> None:
        self._write(t_ns, LogWriter.raw, source, t_ns, data)

    def frame(self, frame: Frame) -> None:
        self._write(frame.t_ns, LogWriter.frame, frame)

    def pose(self, pose: Pose) -> None:
        # encoded now, once with the other sinks (pose_json), written behind
        self._write(pose.t_ns, LogWriter.pose, pose, pose_json(pose, self.view.nav_frame_id))

    def status(self, t_ns: int, status: dict[str, Any]) -> None:
        self.json("/status", t_ns, status, "uwbd.Status")

    def json(self, topic: str, t_ns: int, obj: dict[str, Any], schema_name: str = "") -> None:
        """Any other JSON record (e.g. ``/truth`` when the truth is known); its schema is
        uwbd's of that name (:data:`uwbd.logs.foxglove.SCHEMAS`)."""
        self._write(t_ns, LogWriter.json, topic, t_ns, obj, schema_name)

    def _close_current(self) -> None:
        if self._log is not None:
            try:
                self._log.close()
            except OSError as err:
                self._fail(f"finishing {self._log.path}: {err.strerror or err}", self._opened_ns)
            self._log = None

    def close(self) -> None:
        self.write_pending(everything=True)
        log = self._log
        self._close_current()
        if log is not None and not self.error:
            self._flushed(log)
