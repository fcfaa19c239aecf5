"""The checks of a session's outputs, threads and timing; each raises RuleBroken naming the rule."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench_matrix.backend import Session
from bench_matrix.conformance.cases import RuleBroken, Tolerance
from bench_matrix.measure.metrics import non_finite_reason
from bench_matrix.op_profile import KINDS, PRECISIONS, Profile
from bench_matrix.tensors import Inputs

THREAD_KEYS = ("threads", "intra_op_threads")  # how info() names the intra-op threads in force
# execute() counts as returning before its work is done when, of one call's work, more than this share is
# still pending when it returns (fetch right after it waits that long) and that is at least PENDING_FLOOR_S.
PENDING_SHARE, PENDING_FLOOR_S, PENDING_REPEATS = 0.5, 0.002, 3
PROFILED_CALLS = 2  # calls a profile runs in the kit


def check_fetched(outputs: Any, reference: list[np.ndarray], previous: int | None = None) -> list[np.ndarray]:
    """`outputs` (from predict) as fetch must give them: a list of every output, each finite float32 in the
    reference's shape, batch first; `previous`: the last call's batch, whose outputs these must not be."""
    if not isinstance(outputs, list) or len(outputs) != len(reference):
        count = len(outputs) if isinstance(outputs, (list, tuple)) else "not a list"
        raise RuleBroken("fetch-returns-every-output",
                         f"fetch() gave {count} outputs ({type(outputs).__name__}); the model has "
                         f"{len(reference)}")
    for index, (got, wanted) in enumerate(zip(outputs, reference)):
        if not isinstance(got, np.ndarray) or got.dtype != np.float32:
            kind = got.dtype if isinstance(got, np.ndarray) else type(got).__name__
            raise RuleBroken("fetch-returns-float32", f"output {index} is {kind}, not a float32 numpy array")
        if got.shape != wanted.shape and previous not in (None, len(wanted)) and got.shape[:1] == (previous,):
            raise RuleBroken("outputs-of-this-call", f"output {index} has the previous call's batch of "
                                                     f"{previous}, not this call's {len(wanted)}")
        if got.shape != wanted.shape:
            if sorted(o.shape for o in outputs) == sorted(r.shape for r in reference):
                raise RuleBroken("outputs-in-order", f"output {index} has shape {got.shape}, the model's "
                                                     f"{wanted.shape}: the outputs are in another order")
            raise RuleBroken("batch-axis-first", f"output {index} has shape {got.shape}, the model's "
                                                 f"{wanted.shape} (batch of {len(wanted)} first)")
    if reason := non_finite_reason(outputs):
        raise RuleBroken("outputs-finite", reason)
    return outputs


def check_close(got: list[np.ndarray], wanted: list[np.ndarray], bounds: list[np.ndarray], rule: str,
                what: str) -> None:
    """Every element of every output of `got` within its bound of `wanted` (the worst one in the message)."""
    for index, (a, b, bound) in enumerate(zip(got, wanted, bounds)):
        if a.shape != b.shape:
            raise RuleBroken(rule, f"output {index} has shape {a.shape}, {what} {b.shape}")
        difference = np.abs(a.astype(np.float64) - b)
        allowed = np.broadcast_to(bound, difference.shape)
        worst = np.unravel_index(np.argmax(difference - allowed), difference.shape)
        if not difference[worst] <= allowed[worst]:
            raise RuleBroken(rule, f"output {index} is {difference[worst]:.3g} from {what} at "
                                   f"{tuple(map(int, worst))}; allowed {allowed[worst]:.3g}")


def within(got: list[np.ndarray], wanted: list[np.ndarray], bounds: list[np.ndarray]) -> bool:
    """Whether every output of `got` has the shape of its `wanted` and lies within its bound of it."""
    return all(a.shape == b.shape and bool(np.all(np.abs(a.astype(np.float64) - b) <= bound))
               for a, b, bound in zip(got, wanted, bounds))


def check_order(got: list[np.ndarray], wanted: list[np.ndarray], bounds: list[np.ndarray]) -> None:
    """RuleBroken unless the outputs come in the model's order: where some output is out of bounds, none
    may be within the bounds of another output of the same shape instead."""
    for index, (a, b, bound) in enumerate(zip(got, wanted, bounds)):
        if within([a], [b], [bound]):
            continue
        for other, (b2, bound2) in enumerate(zip(wanted, bounds)):
            if other != index and within([a], [b2], [bound2]):
                raise RuleBroken("outputs-in-order", f"output {index} is the model's output {other}: fetch "
                                                     f"must return the outputs in the model's order")


def check_this_call(got: list[np.ndarray], wanted: list[np.ndarray], previous: list[np.ndarray] | None,
                    bounds: list[np.ndarray]) -> None:
    """RuleBroken where the outputs are out of bounds of this call's reference (`wanted`) but within those of
    the session's call before (`previous`, of other inputs): the session returned that call's outputs."""
    if previous is not None and not within(got, wanted, bounds) and within(got, previous, bounds):
        raise RuleBroken("outputs-of-this-call", "the outputs are those of the call before (of other "
                                                 "inputs): execute and fetch must return this call's")


def check_quantised(got: list[np.ndarray], reference: list[np.ndarray], noise: list[np.ndarray]) -> None:
    """RuleBroken where int8 outputs are all within float noise (`noise`: fp32's bounds) of the fp32
    reference: the artifact runs the fp32 model, whatever it claims."""
    if within(got, reference, noise):
        raise RuleBroken("int8-is-quantised", "the int8 outputs are the fp32 outputs, within float noise: "
                                              "the artifact is not quantised (int8 differs by rounding)")


def check_kept(first: list[np.ndarray], kept: list[np.ndarray]) -> None:
    """RuleBroken unless the arrays a fetch returned (`first`) still hold what they held (`kept`, copies)
    after the next call: fetch must return arrays of its own, not views of a buffer the runtime reuses."""
    for index, (now, then) in enumerate(zip(first, kept)):
        if not np.array_equal(now, then, equal_nan=True):
            raise RuleBroken("fetch-returns-owned-arrays",
                             f"output {index} of one call changed when the next call ran: fetch returned a "
                             f"view of a buffer the runtime reuses; return a copy (np.array(out))")


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


def check_profile(session: Session, inputs: Inputs, precision: str) -> None:
    """RuleBroken unless an implemented Session.profile gives a reason or the asked calls' profile: vocabulary
    operators, times within wall time, precisions fit for the cell (int8: some int8; fp32: none)."""
    begin = time.perf_counter()
    profile = session.profile(session.prepare(inputs), PROFILED_CALLS)
    wall_ms = (time.perf_counter() - begin) * 1e3
    if not isinstance(profile, Profile):
        raise RuleBroken("profile-is-a-profile", f"profile() returned {type(profile).__name__}, not a Profile")
    if profile.reason:
        return
    if (problem := profile.problem()) or profile.calls != PROFILED_CALLS:
        raise RuleBroken("profile-is-a-result", problem or f"asked for {PROFILED_CALLS} calls, the profile "
                                                           f"says {profile.calls}")
    kinds, precisions = {op.kind for op in profile.operators}, {op.precision for op in profile.operators}
    if not kinds <= set(KINDS) or not precisions <= set(PRECISIONS):
        raise RuleBroken("profile-vocabulary", f"kinds {sorted(kinds)} and precisions {sorted(precisions)}; "
                                               f"allowed: {', '.join(KINDS)}; {', '.join(PRECISIONS)}")
    if profile.total_ms > wall_ms:
        raise RuleBroken("profile-within-its-calls", f"the operators add up to {profile.total_ms:.3g} ms over "
                                                     f"the calls, more than the {wall_ms:.3g} ms profile() took")
    if (precision == "int8") != ("int8" in precisions) and precision in ("int8", "fp32"):
        raise RuleBroken("profile-precisions-plausible", f"a {precision} cell's operators ran at "
                                                         f"{', '.join(sorted(precisions))}")
