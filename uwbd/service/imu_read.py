"""The common IMU read in one call of the C core (``uwbd/fusion/_imu_read.c``).

Almost every read of a WitMotion IMU is one accel and one gyro packet that make one sample,
in order, which passes the integrity check, for a running filter. :func:`imu_read_path`
gives :class:`~uwbd.service.pipeline.Pipeline` a function that takes such a read whole
(parser, time spreading, aligner, check, rest window, prediction: what the Python code of
each does, on their own state, to the bit) and returns the sample, or ``None`` having
changed nothing, for anything else, which the Python code then takes as before.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from drivers import ImuSample, Parser
from drivers.wit import ACC_DIV, GYRO_DIV, TEMP_DIV, WitParser
from uwbd.fusion import native

if TYPE_CHECKING:
    from uwbd.service.pipeline import Pipeline

# ImuSample's slots, in field order: the C core fills them as the dataclass's __init__ does
_SAMPLE_FIELDS = tuple(ImuSample.__dict__[f.name] for f in dataclasses.fields(ImuSample))

ImuRead = Callable[[bytes, int], Any]


def imu_read_path(parser: Parser, pipeline: Pipeline, source: str) -> ImuRead | None:
    """``read(data, t_ns)`` for ``source``'s reads, or ``None`` where there is none (not a
    WitMotion IMU, or the C core not built or switched off). The read returns the sample,
    ``(sample, body)`` when the filter's covariance is due
    (:meth:`~uwbd.fusion.filter.Filter.finish_prediction`), or ``None``."""
    core = native.core
    if core is None or type(parser) is not WitParser or pipeline.filter.imu_step is None:
        return None
    # the objects as their namespaces (vars: the live __dict__ of each), which the C core
    # reads and writes as the Python code's attribute access does, at a quarter of the cost
    parts = (vars(parser), vars(parser.stats), pipeline._last_frame_ns,
             pipeline._period_ns, source, vars(pipeline.aligner), ImuSample, _SAMPLE_FIELDS,
             (ACC_DIV, GYRO_DIV, float(TEMP_DIV)), pipeline.filter.step_parts)
    return functools.partial(core.imu_read, parts)
