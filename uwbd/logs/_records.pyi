"""Types of the output log's common IMU read in C (_records.c); LogWriter.read in mcaplog.py
holds the reference it translates."""

from typing import Any

def imu_read(parts: tuple[dict[str, Any], dict[str, Any], type[Any], Any], raw_channel: int,
             imu_channel: int, t_ns: int, data: bytes, sample: Any) -> int: ...
