"""Logs in and out: simulator runs and datasets to MCAP, and MCAP back to frames and truth.

A simulated log carries the simulator's frames as the bytes the devices would send (the
drivers' encoders), on ``/raw/imu`` and ``/raw/uwb``, so it goes through the parsers exactly
like a recorded one. A dataset that holds decoded values only (i-ASL) is written to the
decoded ``/imu`` and ``/uwb`` channels. Ground truth goes to ``/truth``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from drivers import PARSERS
from drivers.emulator import ENCODERS
from drivers.frames import Frame, ImuSample, UwbRanges
from uwbd import config as cfgmod
from uwbd import journal
from uwbd.codec import frame_from_dict, t_ns_of
from uwbd.fusion.core.rotation import Array, quat_from_euler, quat_from_matrix, quat_to_matrix
from uwbd.logs.mcaplog import LogWriter, SourceInfo, pose_message
from uwbd.logs.reading import LogContents
from uwbd.service.ports import BATCH_LEARN_NS, TAIL_AFTER_PERIODS, batch_vmin
from uwbd.service.sample_times import SampleTimes, batched_bauds
from uwbd.tools.evaluate import merge
from uwbd.tools.importer import Dataset
from uwbd.tools.simulator import Simulation, sensor_settings

LOG = journal.get("logs")
FLUSH_EVERY_NS = 1_000_000_000
TRUTH_EVERY = 4  # of the simulator's IMU-rate truth: 50 Hz


def simulation_sources(uwb_driver: str = "nlink") -> tuple[cfgmod.SourceConfig, ...]:
    return (cfgmod.SourceConfig("imu", "wit", "simulated", 921600),
            cfgmod.SourceConfig("uwb", uwb_driver, "simulated", 921600))


def simulation_toml(sim: Simulation, uwb_driver: str = "nlink") -> str:
    """The config of a simulated run: its anchors, mounting, lever arm and sensor specs."""
    c = sim.config
    imu, fusion = sensor_settings(c)
    return cfgmod.to_toml(simulation_sources(uwb_driver), dict(enumerate(c.anchors_m)),
                          c.mounting, c.lever_arm_m, fusion, imu)


SPLIT_READ_FRACTION = 0.3  # of reads a serial port ends inside a packet (docs/wire-formats.md)
BYTE_NS = 10_850  # one byte at 921600 baud, 8N1
MAG_FIELD_RAW = (210.0, 0.0, -390.0)  # the magnetometer's reading of the Earth's field, LSB


def device_sample(frame: ImuSample, yaw_rad: float) -> ImuSample:
    """``frame`` as a WitMotion set to its default output sends it: with its own attitude
    (0x53: level, the heading) and the magnetometer (0x54) beside accel and gyro."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    mx, my, mz = MAG_FIELD_RAW
    return dataclasses.replace(
        frame, angle_deg=(0.0, 0.0, math.degrees(math.atan2(s, c))),
        mag_raw=(round(c * mx + s * my), round(-s * mx + c * my), round(mz)))


class SerialReads:
    """A device's reports cut into reads as a serial port returns them: one report a read,
    but ``SPLIT_READ_FRACTION`` of them split at a random byte (the read returned while the
    report was arriving; its rest comes with the next read, ``BYTE_NS`` a byte later)."""

    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)

    def cut(self, t_ns: int, report: bytes) -> list[tuple[int, bytes]]:
        """The reads of the report whose last byte arrived at ``t_ns``."""
        if len(report) > 1 and self._rng.random() < SPLIT_READ_FRACTION:
            rest = int(self._rng.integers(1, len(report)))
            return [(t_ns - rest * BYTE_NS, report[:-rest]), (t_ns, report[-rest:])]
        return [(t_ns, report)]


class BatchedReads(SerialReads):
    """An IMU's port as the daemon reads it (:meth:`uwbd.service.ports.SerialSource.
    batch_reads`): a read a report (:class:`SerialReads`) until its byte rate is known
    (``BATCH_LEARN_NS``), then a read each time VMIN bytes have arrived (``BATCH_SHARE`` of
    a pose period's): a few reports, ending anywhere inside one; after a pause of
    ``TAIL_AFTER_PERIODS`` pose periods what waited is read, and the rate is learned anew."""

    def __init__(self, seed: int, pose_period_ns: int) -> None:
        super().__init__(seed)
        self.pose_period_ns = pose_period_ns
        self.vmin = 0
        self._learning: tuple[int, int] | None = None  # since when, bytes since
        self._last_ns: int | None = None
        self._pending = b""

    def cut(self, t_ns: int, report: bytes) -> list[tuple[int, bytes]]:
        out: list[tuple[int, bytes]] = []
        last = self._last_ns
        self._last_ns = t_ns
        if last is not None and t_ns - last > TAIL_AFTER_PERIODS * self.pose_period_ns:
            if self._pending:  # the tail, read once the port went quiet
                out.append((last + TAIL_AFTER_PERIODS * self.pose_period_ns, self._pending))
            self._pending, self.vmin, self._learning = b"", 0, None
        if not self.vmin:
            since_ns, count = self._learning or (t_ns, 0)
            if t_ns - since_ns >= BATCH_LEARN_NS:
                rate_bps = count * 1e9 / (t_ns - since_ns)
                self.vmin = batch_vmin(rate_bps, self.pose_period_ns)
            self._learning = (since_ns, count + len(report))
            if not self.vmin:
                return out + super().cut(t_ns, report)
        data = self._pending + report
        start = 0
        while len(data) - start >= self.vmin:  # a read returns as its VMIN-th byte arrives
            end = start + self.vmin
            out.append((t_ns - (len(data) - end) * BYTE_NS, data[start:end]))
            start = end
        self._pending = data[start:]
        return out

    def tail(self) -> list[tuple[int, bytes]]:
        """What waited below VMIN when the device stopped, read then."""
        pending, self._pending = self._pending, b""
        if not pending or self._last_ns is None:
            return []
        return [(self._last_ns + TAIL_AFTER_PERIODS * self.pose_period_ns, pending)]


def write_simulation(sim: Simulation, path: Path, uwb_driver: str = "nlink") -> None:
    """The simulated run as its devices would send it (every packet type a WitMotion sends
    by default, reads split where a serial port splits them, the IMU's batched as the
    daemon reads it) and its truth."""
    sources = simulation_sources(uwb_driver)
    toml = simulation_toml(sim, uwb_driver)
    infos = tuple(SourceInfo(s.name, s.driver, s.port) for s in sources)
    encode = {"imu": ENCODERS["wit"], "uwb": ENCODERS[uwb_driver]}
    imu_reads = BatchedReads(sim.config.seed * 2, cfgmod.parse(toml, "simulation").pose_period_ns)
    reads = {"imu": imu_reads, "uwb": SerialReads(sim.config.seed * 2 + 1)}
    with LogWriter(path, toml, infos) as log:
        next_flush = sim.truth_t_ns[0] + FLUSH_EVERY_NS
        truth_k = 0
        last_ns = -(2**63)
        for frame in merge(sim.imu, sim.uwb):
            if isinstance(frame, ImuSample):
                k = max(int(np.searchsorted(sim.truth_t_ns, frame.t_ns, side="right")) - 1, 0)
                report = encode["imu"](device_sample(frame, float(sim.truth_yaw_rad[k])))
                source = "imu"
            else:
                source, report = "uwb", encode["uwb"](frame)
            for t_ns, data in reads[source].cut(frame.t_ns, report):
                last_ns = max(last_ns, t_ns)  # a log's reads in arrival order
                log.raw(source, last_ns, data)
            while truth_k < len(sim.truth_t_ns) and sim.truth_t_ns[truth_k] <= frame.t_ns:
                t = int(sim.truth_t_ns[truth_k])
                w, x, y, z = quat_from_euler(0.0, 0.0, float(sim.truth_yaw_rad[truth_k]))
                log.json("/truth", t, pose_message(t, sim.truth_p_m[truth_k], (x, y, z, w)),
                         "foxglove.PoseInFrame")
                truth_k += TRUTH_EVERY
            if frame.t_ns >= next_flush:
                log.flush()
                next_flush += FLUSH_EVERY_NS
        for t_ns, data in imu_reads.tail():
            log.raw("imu", max(last_ns, t_ns), data)


def write_dataset(ds: Dataset, path: Path, mounting: Sequence[Sequence[float]],
                  lever_arm_m: Sequence[float] = (0.0, 0.0, 0.0),
                  progress: bool = False) -> None:
    """The dataset as a log of decoded frames and truth; its config holds the anchors, the
    IMU mounting (sensor -> body) and the IMU-to-antenna lever arm, fusion at defaults.
    ``progress``: a bar on stderr."""
    toml = cfgmod.to_toml((), ds.anchors_m, mounting, lever_arm_m,
                          anchor_orientations_xyzw=ds.anchor_orientations_xyzw)
    with LogWriter(path, toml) as log:
        for frame in tqdm(merge(ds.imu, ds.uwb), total=len(ds.imu) + len(ds.uwb),
                          desc="import", unit="frame", disable=not progress, leave=False,
                          mininterval=0.5):
            log.frame(frame)
        for t, p, r in zip(ds.truth_t_ns, ds.truth_p_m, ds.truth_rotation, strict=True):
            w, x, y, z = quat_from_matrix(r)
            log.json("/truth", int(t), pose_message(int(t), p, (x, y, z, w)),
                     "foxglove.PoseInFrame")


@dataclass
class Recording:
    """What a log holds for fusion: its config, frames in time order, and truth if any."""

    config: cfgmod.Config
    frames: list[Frame]
    truth_t_ns: npt.NDArray[np.int64]
    truth_p_m: Array
    parser_stats: dict[str, dict[str, object]]
    truth_rotation: Array  # (n, 3, 3) body -> navigation frame (identity where a log has none)


def load_recording(contents: LogContents, where: str,
                   config_toml: str | None = None) -> Recording:
    """Decode a log: raw channels through the drivers named in its metadata, else the
    decoded channels. The config comes from the log's metadata unless ``config_toml``."""
    config = (cfgmod.parse(contents.metadata.get("config_toml", ""), f"{where} (metadata)")
              if config_toml is None else cfgmod.parse(config_toml, f"{where} (with -c/--set)"))
    sources = json.loads(contents.metadata.get("sources", "[]") or "[]")
    raw_topics = {f"/raw/{s['name']}": s for s in sources}
    imu: list[ImuSample] = []
    uwb: list[UwbRanges] = []
    stats: dict[str, dict[str, object]] = {}
    if any(m.topic in raw_topics for m in contents.messages):
        parsers = {topic: PARSERS[s["driver"]]() for topic, s in raw_topics.items()}
        # a read's frames spread as the daemon spreads them
        times = SampleTimes(batched_bauds(config.sources, "/raw/"))
        for m in contents.messages:
            parser = parsers.get(m.topic)
            if parser is not None:
                _sort(times.spread(m.topic, parser.feed(m.data, m.log_time_ns), len(m.data)),
                      imu, uwb)
        for topic, parser in parsers.items():
            _sort(times.spread(topic, parser.flush()), imu, uwb)
            stats[topic] = parser.stats.as_dict()
    else:
        _sort(decoded_frames(contents, ("/imu", "/uwb"), where), imu, uwb)
    t, p, q = truth_poses(contents, where)
    imu.sort(key=lambda f: f.t_ns)
    uwb.sort(key=lambda f: f.t_ns)
    return Recording(config, list(merge(imu, uwb)), t, p, stats,
                     np.array([quat_to_matrix(x) for x in q]).reshape(-1, 3, 3))


def truth_poses(contents: LogContents, where: str) -> tuple[npt.NDArray[np.int64], Array,
                                                              Array]:
    """``/truth``: times, positions and unit quaternions (w, x, y, z; identity where a record
    has no orientation). A record that is not a pose (another program's channel of the
    name) is skipped, and said once with how many were."""
    t, p, q = [], [], []
    bad, first = 0, ""
    for d in contents.json("/truth"):
        try:
            pose = d["pose"]
            orientation = pose.get("orientation", {})
            row = [float(pose["position"][k]) for k in "xyz"]
            quat = [float(orientation.get(k, 1.0 if k == "w" else 0.0)) for k in "wxyz"]
            t_ns = t_ns_of(d["t_ns"])
            if not all(map(math.isfinite, row + quat)):
                raise ValueError("a position or orientation that is not a finite number")
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            bad += 1
            first = first or f"{type(err).__name__}: {err}"
            continue
        t.append(t_ns)
        p.append(row)
        q.append(quat)
    if bad:
        LOG.warning("%s: %d of %d /truth records are not poses and were skipped (the first: "
                    "%s)", where, bad, bad + len(t), first)
    quats = np.array(q, dtype=float).reshape(-1, 4)
    quats /= np.maximum(np.linalg.norm(quats, axis=1), 1e-12)[:, None]
    return (np.array(t, dtype=np.int64), np.array(p, dtype=float).reshape(-1, 3), quats)


def decoded_frames(contents: LogContents, topics: tuple[str, ...], where: str) -> list[Frame]:
    """The frames of the decoded channels ``topics``, in log order; a record that is not one
    (a damaged log, or another program's channel of the same name) is skipped, and said
    once with how many were."""
    frames: list[Frame] = []
    bad, first = 0, ""
    for m in contents.messages:
        if m.topic in topics:
            try:
                frames.append(frame_from_dict(json.loads(m.data)))
            except (ValueError, KeyError, TypeError, IndexError) as err:
                bad += 1
                first = first or f"the first, a {m.topic} record at {m.log_time_ns} ns: {err}"
    if bad:
        LOG.warning("%s: %d of %d %s records are not frames and were skipped (%s)", where,
                    bad, bad + len(frames), ", ".join(topics), first)
    return frames


def _sort(frames: Iterable[Frame], imu: list[ImuSample], uwb: list[UwbRanges]) -> None:
    for f in frames:
        if isinstance(f, ImuSample):
            imu.append(f)
        elif isinstance(f, UwbRanges):  # anchor-to-anchor ranges are not the tag's
            uwb.append(f)
