"""torch.profiler's per-operator profile of a torch session on the CPU (eager, TorchScript, torch.compile,
AOTInductor): each recorded op's self CPU time, summed per op and precision over the calls."""

from __future__ import annotations

import re
from collections.abc import Callable
from contextlib import nullcontext
from typing import TYPE_CHECKING, Any

from bench_matrix.plugin import OperatorTime, Profile, kind_of

if TYPE_CHECKING:
    from torch.autograd.profiler_util import FunctionEvent

# a call under the profiler before the profiled ones, its events dropped: it takes the profiler's first-call
# costs, and its event names the thread that makes the calls
WARM_UP = "bench_matrix::warm_up"
INT8_PREFIXES = ("quantized::", "onednn::q")  # quantized::linear_dynamic, quantized::conv2d, onednn::qconv2d
# an input's dtype as torch.profiler names it (record_shapes) -> the precision an op reading it runs at
DTYPE_PRECISIONS = {"c10::quint8": "int8", "c10::qint8": "int8", "signed char": "int8", "float": "fp32",
                    "c10::Half": "fp16", "c10::BFloat16": "bf16"}
COMPILED_GRAPH = re.compile(r"## Call CompiledFxGraph \w+ ##")  # torch.compile's call of a compiled graph


def torch_profile(call: Callable[[], Any], calls: int, compute_precision: str,
                  wrap: str | None = None) -> Profile:
    """`call` run once unprofiled, once under torch.profiler (CPU, input dtypes recorded) with its events
    dropped, then `calls` times; an op without a typed input (a compiled region) is put at
    `compute_precision`. With `wrap`, each call runs in a record_function of that name, whose self time (the
    call's time in no recorded op) is an operator too."""
    from torch.profiler import ProfilerActivity, profile, record_function

    call()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as profiler:
        with record_function(WARM_UP):
            call()
        for _ in range(calls):
            with record_function(wrap) if wrap else nullcontext():
                call()
    return Profile(operators(profiler.events(), compute_precision), calls)


def operators(events: list["FunctionEvent"], compute_precision: str) -> tuple[OperatorTime, ...]:
    """Self CPU time (µs) per (op, precision) in ms, over the events after the warm-up on its thread.

    Self time, not total time: an op's total holds its nested ops' (aten::linear holds aten::addmm), and a
    torch.compile'd call's top-level region holds everything, so only self times add up without counting
    anything twice. Ops that intra-op worker threads record overlap their caller's time: they are left out,
    their work being in the time of the op that waited for them."""
    warm_up = next(event for event in events if event.name == WARM_UP)
    found: dict[tuple[str, str], float] = {}
    for event in events:
        if event.thread == warm_up.thread and event.time_range.start >= warm_up.time_range.end \
                and not event.is_async:
            key = (event.name, precision(event.name, event.input_dtypes or (), compute_precision))
            found[key] = found.get(key, 0.0) + event.self_cpu_time_total / 1000
    return tuple(OperatorTime(name, (op_type := op_type_of(name)), kind_of(op_type), chosen, ms)
                 for (name, chosen), ms in found.items())


def op_type_of(name: str) -> str:
    """The op type of an event: its name, but CompiledFxGraph for a compiled graph's call (whose name has a
    hash, whose letters could spell a kind's word)."""
    return "CompiledFxGraph" if COMPILED_GRAPH.fullmatch(name) else name


def precision(name: str, dtypes: Any, compute_precision: str) -> str:
    """int8 for a quantized op or one reading a quantized or int8 tensor, else its first floating input's
    precision; `compute_precision` when no input has a dtype named in DTYPE_PRECISIONS."""
    known = [DTYPE_PRECISIONS[dtype] for dtype in dtypes if dtype in DTYPE_PRECISIONS]
    if name.startswith(INT8_PREFIXES) or "int8" in known:
        return "int8"
    return known[0] if known else compute_precision
