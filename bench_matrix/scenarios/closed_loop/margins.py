"""A cell's margins: each margin the section asks for, searched on each margin circuit with lock-step laps of
the cell's own session (docs/closed-loop.md, "Margins")."""

from __future__ import annotations

import time
from typing import Any

from bench_matrix.phases import phase
from bench_matrix.scenarios.closed_loop.spec import MARGIN_RANGES, MarginSpec
from bench_matrix.workload.driving.circuit import Track
from bench_matrix.workload.driving.lap import SimSettings
from bench_matrix.workload.driving.margins import lap_probe, search
from bench_matrix.workload.driving.simulator import Brain


def search_margins(brain: Brain, margins: tuple[MarginSpec, ...],
                   circuits: dict[str, tuple[Track, SimSettings]]) -> dict[str, dict[str, Any]]:
    """{circuit: {margin: its search's answer, range, laps and wall time}} for the record's
    `closed_loop_margins`."""
    found: dict[str, dict[str, Any]] = {}
    for name, (circuit, settings) in circuits.items():
        found[name] = {}
        for margin in margins:
            phase(f"closed loop · margins · {name} · {margin.kind}")
            begin = time.perf_counter()
            probe = lap_probe(margin.kind, circuit, brain, settings, margin.perturbation, margin.seed)
            answer = search(probe, margin.knob)
            found[name][margin.kind] = {
                **answer.as_dict(), "start": margin.knob.start, "limit": margin.knob.top,
                "unit": MARGIN_RANGES[margin.kind][3], "laps": len(answer.probes),
                "wall_s": time.perf_counter() - begin,
                **({"perturbation": margin.perturbation, "seed": margin.seed} if margin.kind == "perception"
                   else {})}
    return found
