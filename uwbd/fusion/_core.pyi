"""Types of the C core (_core.c); eskf.py holds the reference each function translates."""

from collections.abc import Callable, Sequence
from typing import Any

def predict(p: list[float], v: list[float], q: Sequence[float], b_g: Sequence[float],
            b_a: Sequence[float], sum_fn: list[float], sum_w: list[float],
            acc_b: Sequence[float], gyro_b: Sequence[float], dt: float,
            gravity: float) -> list[float]: ...
def propagate_core(P: Any, Phi_epoch: Any, q: Sequence[float], sum_fn: Sequence[float],
                   sum_w: Sequence[float], T: float, q_rate: Any) -> None: ...
def sequential_update(P: Any, H: Any, y: Any, R: Any,
                      decide: Callable[[int, float, float], float], c0: int, c1: int,
                      dx: Any) -> list[tuple[float, float, float, bool]]: ...
def gauss_newton(anchors: Any, ranges: Any, x: Any, dims: int, max_iterations: int,
                 converged_m: float, accept_last_m: float, out: Any) -> int: ...
def leverages(anchors: Any, x: Any, dims: int) -> list[float] | None: ...
