"""Importers: recorded datasets turned into uwbd frames and ground truth.

``iasl``: the i-ASL UWB/IMU dataset layout (``imu.csv``, ``uwb.csv``, ``gt.csv``, see
``shared/data/iasl-s1/README.md``): a Nooploop LinkTrack tag with 8 anchors, a UM7 IMU
mounted z-down, Qualisys ground truth, all on the recording host's clock (Unix seconds).
Ranges ``d1..d8`` become anchor ids 0..7 (the TagFrame0 slots), 0 meaning "no range".

``inrol``: the INRoL UWB localisation dataset layout (``anchor.txt``, ``imu.txt``,
``uwb.txt``, ``imu_pose.txt``, see ``shared/data/inrol-env1/README.md``): space-separated
with a ``#`` header line, times in seconds from the start of the recording, one range per
line (a tag ranging one anchor at a time), anchor ids as in the files. The IMU is z up and
the truth is the IMU's own pose, so the body frame is the IMU frame (mounting identity);
the tag antenna sits :data:`INROL_LEVER_ARM_M` from the IMU. Its range-model calibration
recording (``tag_pose.txt`` in place of ``imu.txt`` and ``imu_pose.txt``, see
``shared/data/inrol-calib/README.md``) has no IMU and the tag's own pose as truth: the body
frame is the tag's, and the lever arm zero.

Every file problem (missing file, wrong header or column count, a value that is not a
number) is a :class:`DatasetError` naming the file and line. Rows are put in time order.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.fusion.core.rotation import Array, quat_to_matrix
from uwbd.fusion.settings import IDENTITY3, Z_DOWN

IASL_ANCHORS_M: dict[int, tuple[float, float, float]] = {
    i: (x, y, z) for i, (x, y, z) in enumerate(zip(
        (0, 0, 8.86, 8.86, 0, 0, 8.86, 8.86), (0, 8.00, 8.00, 0, 0, 8.00, 8.00, 0),
        (0, 0, 0, 0, 2.20, 2.20, 2.20, 2.20), strict=True))
}

INROL_EPOCH_NS = 1_700_000_000 * 10**9
"""Added to every inrol time: the files' clock starts at 0 with the recording, so the run is
put on a stated epoch, the simulator's (``uwbd.tools.simulator.EPOCH_NS``, 2023-11-14T22:13:20Z)."""
INROL_MOUNTING = IDENTITY3  # the truth is the IMU's pose: body frame = IMU frame
INROL_LEVER_ARM_M = (0.0, 0.0, 0.01)  # IMU -> tag antenna, IMU axes (the dataset's README)

T = TypeVar("T")


class DatasetError(ValueError):
    """A dataset file that does not have the expected layout (file, line, column)."""


@dataclass
class Dataset:
    imu: list[ImuSample]
    uwb: list[UwbRanges]
    truth_t_ns: npt.NDArray[np.int64]
    truth_p_m: Array
    truth_rotation: Array  # (n, 3, 3) body-to-anchor-frame rotations
    anchors_m: dict[int, tuple[float, float, float]]
    mounting: tuple[tuple[float, float, float], ...] = IDENTITY3  # IMU axes -> body
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU -> tag antenna, body axes
    # the anchors' antenna orientations where the dataset gives them: (x, y, z, w), the
    # anchor's axes -> the anchors' frame
    anchor_orientations_xyzw: dict[int, tuple[float, float, float, float]] = \
        field(default_factory=dict)

    @property
    def anchor_axes(self) -> dict[int, Array]:
        """The anchors' orientations as rotations (anchor axes -> frame)."""
        return {a: quat_to_matrix(np.array([w, x, y, z]))
                for a, (x, y, z, w) in self.anchor_orientations_xyzw.items()}


_DECIMAL = re.compile(r"([+-]?)(\d*)(?:\.(\d*))?")


def seconds_to_ns(text: str) -> int:
    """``"1718170318.393996477"`` -> ns, exactly (no float rounding; digits beyond the
    nanosecond are cut off). Anything but a plain decimal number is a ``ValueError``."""
    m = _DECIMAL.fullmatch(text.strip())
    if m is None or not (m[2] or m[3]):
        raise ValueError(f"not a decimal number of seconds: {text!r}")
    ns = int(m[2] or "0") * 1_000_000_000 + int(((m[3] or "") + "000000000")[:9])
    return -ns if m[1] == "-" else ns


def _rows(path: Path, columns: Sequence[str], spaces: bool = False
          ) -> list[tuple[int, list[str]]]:
    """The data rows of a table file with their line numbers, after checking the header
    (CSV; or, with ``spaces``, whitespace-separated under a ``# col col ...`` line). Blank
    lines are skipped; every other row must have one value per column."""
    try:
        with path.open(newline="") as f:
            records: Iterator[tuple[int, list[str]]]
            if spaces:
                records = enumerate((line.split() for line in f), start=1)
            else:
                reader = csv.reader(f)
                records = ((reader.line_num, row) for row in reader)
            _, header = next(records, (1, None))
            sep = " " if spaces else ","
            got = None if header is None else sep.join(header)
            if spaces and got is not None and got.startswith("#"):
                header = got.removeprefix("#").split()
            elif spaces:
                header = None
            if header != list(columns):
                expected = ("# " if spaces else "") + sep.join(columns)
                raise DatasetError(f"{path}: line 1: expected the header {expected!r}, got "
                                   + ("nothing" if got is None else repr(got)))
            rows = []
            for line, row in records:
                if not row:
                    continue
                if len(row) != len(columns):
                    raise DatasetError(f"{path}: line {line}: expected {len(columns)} values,"
                                       f" got {len(row)}")
                rows.append((line, row))
    except OSError as err:
        raise DatasetError(f"{path}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise DatasetError(f"{path}: not a text file (byte {err.start}: {err.reason})") from err
    if not rows:
        raise DatasetError(f"{path}: no data after the header")
    return rows


def _cell(path: Path, line: int, column: str, text: str, convert: Callable[[str], T]) -> T:
    try:
        value = convert(text)
    except ValueError:
        what = "an integer" if convert is int else "a number"
        raise DatasetError(f"{path}: line {line}: {column}: not {what}: {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise DatasetError(f"{path}: line {line}: {column}: not a finite number: {text!r}")
    return value


def _floats(path: Path, line: int, columns: Sequence[str], row: Sequence[str]) -> list[float]:
    return [_cell(path, line, c, x, float) for c, x in zip(columns, row, strict=True)]


def _dataset(imu: list[ImuSample], uwb: list[UwbRanges], truth_t_ns: list[int],
             truth_p_m: list[list[float]], truth_rotation: list[Array],
             anchors_m: dict[int, tuple[float, float, float]],
             mounting: tuple[tuple[float, float, float], ...] = IDENTITY3,
             lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Dataset:
    """The dataset with every stream in time order (stable: equal times keep file order)."""
    t = np.array(truth_t_ns, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    return Dataset(sorted(imu, key=lambda f: f.t_ns), sorted(uwb, key=lambda f: f.t_ns),
                   t[order], np.array(truth_p_m, dtype=float).reshape(-1, 3)[order],
                   np.array(truth_rotation, dtype=float).reshape(-1, 3, 3)[order], anchors_m,
                   mounting, lever_arm_m)


def load_iasl(directory: Path) -> Dataset:
    imu_path, uwb_path, gt_path = directory / "imu.csv", directory / "uwb.csv", directory / "gt.csv"
    imu = []
    cols = ["t", "ax", "ay", "az", "gx", "gy", "gz"]
    for line, row in _rows(imu_path, cols):
        ax, ay, az, gx, gy, gz = _floats(imu_path, line, cols[1:], row[1:])
        imu.append(ImuSample(_cell(imu_path, line, "t", row[0], seconds_to_ns),
                             (ax, ay, az), (gx, gy, gz)))
    uwb = []
    cols = ["t", *(f"d{k}" for k in range(1, 9)), "vx", "vy", "vz"]
    for line, row in _rows(uwb_path, cols):
        values = _floats(uwb_path, line, cols[1:], row[1:])
        ranges = tuple(AnchorRange(k, d) for k, d in enumerate(values[:8]) if d != 0.0)
        x, y, z = values[8:]
        uwb.append(UwbRanges(_cell(uwb_path, line, "t", row[0], seconds_to_ns), ranges,
                             tag_position_m=(x, y, z)))
    cols = ["t", "x", "y", "z", *(f"r{i}{j}" for i in range(3) for j in range(3))]
    t_ns, p, rot = [], [], []
    for line, row in _rows(gt_path, cols):
        values = _floats(gt_path, line, cols[1:], row[1:])
        t_ns.append(_cell(gt_path, line, "t", row[0], seconds_to_ns))
        p.append(values[:3])
        rot.append(np.array(values[3:]).reshape(3, 3))
    return _dataset(imu, uwb, t_ns, p, rot, dict(IASL_ANCHORS_M), Z_DOWN)


def _inrol_time(path: Path, line: int, text: str) -> int:
    return INROL_EPOCH_NS + _cell(path, line, "timestamp", text, seconds_to_ns)


def load_inrol(directory: Path) -> Dataset:
    """An inrol directory: anchor positions and antenna orientations, IMU
    samples (gyro columns first in the file), ranges, and the IMU's true pose, every time
    on :data:`INROL_EPOCH_NS`; or, where ``tag_pose.txt`` stands in for ``imu_pose.txt``, a
    range-model calibration recording: no IMU, the tag's pose as truth. Ranges with exactly
    the same timestamp become one ``UwbRanges`` message, any other range a message of its
    own."""
    anchor_path, imu_path = directory / "anchor.txt", directory / "imu.txt"
    uwb_path, pose_path = directory / "uwb.txt", directory / "imu_pose.txt"
    calibration = not pose_path.exists() and (directory / "tag_pose.txt").exists()
    if calibration:
        pose_path = directory / "tag_pose.txt"
    anchors: dict[int, tuple[float, float, float]] = {}
    orientations: dict[int, tuple[float, float, float, float]] = {}
    cols = ["anchor_id", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    for line, row in _rows(anchor_path, cols, spaces=True):
        anchor_id = _cell(anchor_path, line, "anchor_id", row[0], int)
        if anchor_id in anchors:
            raise DatasetError(f"{anchor_path}: line {line}: anchor {anchor_id} listed twice")
        x, y, z = _floats(anchor_path, line, cols[1:4], row[1:4])
        anchors[anchor_id] = (x, y, z)
        orientations[anchor_id] = _unit_quaternion(anchor_path, line, cols[4:], row[4:])
    imu = []
    cols = ["index", "timestamp", "wx", "wy", "wz", "ax", "ay", "az"]
    for line, row in [] if calibration else _rows(imu_path, cols, spaces=True):
        _cell(imu_path, line, "index", row[0], int)
        wx, wy, wz, ax, ay, az = _floats(imu_path, line, cols[2:], row[2:])
        imu.append(ImuSample(_inrol_time(imu_path, line, row[1]), (ax, ay, az), (wx, wy, wz)))
    ranges_at: dict[int, list[AnchorRange]] = {}
    for line, row in _rows(uwb_path, ["index", "timestamp", "anchor_id", "r"], spaces=True):
        _cell(uwb_path, line, "index", row[0], int)
        anchor_id = _cell(uwb_path, line, "anchor_id", row[2], int)
        if anchor_id not in anchors:
            raise DatasetError(f"{uwb_path}: line {line}: anchor {anchor_id} is not in "
                               f"{anchor_path.name}")
        ranges_at.setdefault(_inrol_time(uwb_path, line, row[1]), []).append(
            AnchorRange(anchor_id, _cell(uwb_path, line, "r", row[3], float)))
    uwb = [UwbRanges(t, tuple(ranges)) for t, ranges in ranges_at.items()]
    cols = ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    t_ns, p, rot = [], [], []
    for line, row in _rows(pose_path, cols, spaces=True):
        x, y, z = _floats(pose_path, line, cols[1:4], row[1:4])
        qx, qy, qz, qw = _unit_quaternion(pose_path, line, cols[4:], row[4:])
        t_ns.append(_inrol_time(pose_path, line, row[0]))
        p.append([x, y, z])
        rot.append(quat_to_matrix(np.array([qw, qx, qy, qz])))
    if calibration:  # the truth is the tag's own pose: body frame = tag frame
        ds = _dataset(imu, uwb, t_ns, p, rot, anchors)
    else:
        ds = _dataset(imu, uwb, t_ns, p, rot, anchors, INROL_MOUNTING, INROL_LEVER_ARM_M)
    ds.anchor_orientations_xyzw = orientations
    return ds


def _unit_quaternion(path: Path, line: int, cols: list[str], cells: list[str]
                     ) -> tuple[float, float, float, float]:
    """Cells ``qx qy qz qw`` as a unit quaternion (x, y, z, w)."""
    qx, qy, qz, qw = _floats(path, line, cols, cells)
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not abs(norm - 1.0) < 1e-3:
        raise DatasetError(f"{path}: line {line}: quaternion of norm {norm:.6g}, expected a "
                           "unit quaternion")
    return (qx / norm, qy / norm, qz / norm, qw / norm)
