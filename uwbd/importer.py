"""Importers: recorded datasets turned into uwbd frames and ground truth.

``iasl``: the i-ASL UWB/IMU dataset layout (``imu.csv``, ``uwb.csv``, ``gt.csv``, see
``shared/data/iasl-s1/README.md``): a Nooploop LinkTrack tag with 8 anchors, a UM7 IMU
mounted z-down, Qualisys ground truth, all on the recording host's clock (Unix seconds).
Ranges ``d1..d8`` become anchor ids 0..7 (the TagFrame0 slots), 0 meaning "no range".
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.fusion.rotation import Array

IASL_ANCHORS_M: dict[int, tuple[float, float, float]] = {
    i: (x, y, z) for i, (x, y, z) in enumerate(zip(
        (0, 0, 8.86, 8.86, 0, 0, 8.86, 8.86), (0, 8.00, 8.00, 0, 0, 8.00, 8.00, 0),
        (0, 0, 0, 0, 2.20, 2.20, 2.20, 2.20), strict=True))
}


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


def seconds_to_ns(text: str) -> int:
    """``"1718170318.393996477"`` -> ns, exactly (no float rounding)."""
    whole, _, frac = text.strip().partition(".")
    return int(whole) * 1_000_000_000 + int((frac + "000000000")[:9])


def _rows(path: Path, columns: list[str]) -> list[list[str]]:
    try:
        with path.open(newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header != columns:
                raise DatasetError(f"{path}: line 1: expected columns {columns}, got {header}")
            rows = []
            for line, row in enumerate(reader, start=2):
                if len(row) != len(columns):
                    raise DatasetError(f"{path}: line {line}: expected {len(columns)} values,"
                                       f" got {len(row)}")
                rows.append(row)
            return rows
    except OSError as err:
        raise DatasetError(f"{path}: {err.strerror}") from err


def _floats(path: Path, row: list[str], line: int) -> list[float]:
    try:
        return [float(x) for x in row[1:]]
    except ValueError as err:
        raise DatasetError(f"{path}: line {line}: {err}") from err


def load_iasl(directory: Path) -> Dataset:
    imu_path, uwb_path, gt_path = directory / "imu.csv", directory / "uwb.csv", directory / "gt.csv"
    imu = []
    for line, row in enumerate(_rows(imu_path, ["t", "ax", "ay", "az", "gx", "gy", "gz"]), 2):
        ax, ay, az, gx, gy, gz = _floats(imu_path, row, line)
        imu.append(ImuSample(seconds_to_ns(row[0]), (ax, ay, az), (gx, gy, gz)))
    uwb = []
    cols = ["t", *(f"d{k}" for k in range(1, 9)), "vx", "vy", "vz"]
    for line, row in enumerate(_rows(uwb_path, cols), 2):
        values = _floats(uwb_path, row, line)
        ranges = tuple(AnchorRange(k, d) for k, d in enumerate(values[:8]) if d != 0.0)
        x, y, z = values[8:]
        uwb.append(UwbRanges(seconds_to_ns(row[0]), ranges, tag_position_m=(x, y, z)))
    gt_cols = ["t", "x", "y", "z", *(f"r{i}{j}" for i in range(3) for j in range(3))]
    gt = _rows(gt_path, gt_cols)
    truth = np.array([_floats(gt_path, row, line) for line, row in enumerate(gt, 2)])
    t_ns = np.array([seconds_to_ns(row[0]) for row in gt], dtype=np.int64)
    return Dataset(imu, uwb, t_ns, truth[:, :3], truth[:, 3:].reshape(-1, 3, 3),
                   dict(IASL_ANCHORS_M))
