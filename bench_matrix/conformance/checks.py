"""The checks of a session's outputs, threads and timing; each raises RuleBroken naming the rule."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench_matrix.backend import Session
from bench_matrix.conformance.cases import RuleBroken, Tolerance
from bench_matrix.measure.metrics import non_finite_reason
from bench_matrix.tensors import Inputs

THREAD_KEYS = ("threads", "intra_op_threads")  # how info() names the intra-op threads in force
# execute() counts as returning before its work is done when, of one call's work, more than this share is
# still pending when it returns (fetch right after it waits that long) and that is at least PENDING_FLOOR_S.
PENDING_SHARE, PENDING_FLOOR_S, PENDING_REPEATS = 0.5, 0.002, 3


def check_fetched(outputs: Any, reference: list[np.ndarray]) -> list[np.ndarray]:
    """`outputs` (what predict returned) as fetch must give them: a list with every output, each a finite
    float32 array of the reference's shape, batch axis first."""
    if not isinstance(outputs, list) or len(outputs) != len(reference):
        count = len(outputs) if isinstance(outputs, (list, tuple)) else "not a list"
        raise RuleBroken("fetch-returns-every-output",
                         f"fetch() gave {count} outputs ({type(outputs).__name__}); the model has "
                         f"{len(reference)}")
    for index, (got, wanted) in enumerate(zip(outputs, reference)):
        if not isinstance(got, np.ndarray) or got.dtype != np.float32:
            kind = got.dtype if isinstance(got, np.ndarray) else type(got).__name__
            raise RuleBroken("fetch-returns-float32", f"output {index} is {kind}, not a float32 numpy array")
        if got.shape != wanted.shape:
            raise RuleBroken("batch-axis-first", f"output {index} has shape {got.shape}, the model's "
                                                 f"{wanted.shape} (batch of {len(wanted)} first)")
    if reason := non_finite_reason(outputs):
        raise RuleBroken("outputs-finite", reason)
    return outputs


def check_close(got: list[np.ndarray], wanted: list[np.ndarray], bounds: list[np.ndarray], rule: str,
                what: str) -> None:
    """Every element of every output of `got` within its bound of `wanted` (the worst one in the message)."""
    for index, (a, b, bound) in enumerate(zip(got, wanted, bounds)):
        difference = np.abs(a.astype(np.float64) - b)
        allowed = np.broadcast_to(bound, difference.shape)
        worst = np.unravel_index(np.argmax(difference - allowed), difference.shape)
        if not difference[worst] <= allowed[worst]:
            raise RuleBroken(rule, f"output {index} is {difference[worst]:.3g} from {what} at "
                                   f"{tuple(map(int, worst))}; allowed {allowed[worst]:.3g}")


def bounds(tolerance: Tolerance, reference: list[np.ndarray]) -> list[np.ndarray]:
    return [tolerance.bound(out) for out in reference]


def reported_threads(info: Any, threads: int) -> str | None:
    """Why `info` (a session's info()) does not report `threads` intra-op threads in force, or None."""
    if not isinstance(info, dict) or not any(key in info for key in THREAD_KEYS):
        return (f"info() must name the threads in force as 'threads' (or 'intra_op_threads'); it returned "
                f"{info!r}")
    key = next(key for key in THREAD_KEYS if key in info)
    if info[key] == threads:
        return None
    return f"asked for {threads} threads, info() reports {key}={info[key]!r}"


def pending_work(session: Session, inputs: Inputs) -> str | None:
    """Why `execute` seems to return before its work is done, or None: fetch straight after execute waits for
    the work (median of PENDING_REPEATS) much longer than fetch once the work is surely over."""
    prepared = session.prepare(inputs)
    session.fetch(session.execute(prepared))  # warm-up: lazy initialisation is not pending work
    executes, straight, settled = [], [], []
    for _ in range(PENDING_REPEATS):
        begin = time.perf_counter()
        outputs = session.execute(prepared)
        returned = time.perf_counter()
        session.fetch(outputs)
        executes.append(returned - begin)
        straight.append(time.perf_counter() - returned)
        outputs = session.execute(prepared)
        time.sleep(executes[-1] + straight[-1] + PENDING_FLOOR_S)  # any work left is over by then
        begin = time.perf_counter()
        session.fetch(outputs)
        settled.append(time.perf_counter() - begin)
    execute, pending = float(np.median(executes)), float(np.median(straight) - np.median(settled))
    if pending > max(PENDING_SHARE * (execute + pending), PENDING_FLOOR_S):
        return (f"execute() took {execute * 1e3:.2f} ms but fetch() straight after it waited "
                f"{pending * 1e3:.2f} ms more than once the work was over: execute must wait for its work "
                f"(synchronise the device)")
    return None
