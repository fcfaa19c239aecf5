"""What a profiled cell's record adds for the roofline (docs/metrics.md §17): the work of one inference from
its conversion's manifest, and the machine's peak at the cell's thread count, measured once per host, CPU and
thread count (up to ATTEMPTS times while disturbed) and kept in the workspace."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from typing import Any

from bench_matrix.measure.cpu import this_cpu
from bench_matrix.measure.env import host_name
from bench_matrix.measure.interference import LIMITS, between, read_counts
from bench_matrix.measure.peak import best_of, measure, ort_kernels
from bench_matrix.phases import phase
from bench_matrix.workspace import Workspace, digest

WORK_FIELDS = ("flops", "bytes", "weight_bytes", "activation_bytes")
ATTEMPTS = 3  # measurements of a peak that stay disturbed before the best of them is kept as it is


def work_fields(backend: str, meta: dict[str, Any]) -> dict[str, Any]:
    """`work_*` from the conversion's `work` (its fp32 ONNX graph's), or `work_reason`."""
    work = meta.get("work")
    if not isinstance(work, dict):
        return {"work_reason": f"{backend}: its conversion counts no work (onnxruntime and openvino count "
                               f"their fp32 ONNX graph's)"}
    if "reason" in work:
        return {"work_reason": f"{backend}: {work['reason']}"}
    return {f"work_{name}": work[name] for name in WORK_FIELDS}


def peak_fields(workspace: Workspace, threads: int) -> dict[str, Any]:
    """`machine_*` fields at `threads`: measured once here (a few s) and kept; if other work disturbed it, it
    says so and later profiled cells remeasure it, up to ATTEMPTS times, best kept; else `machine_reason`."""
    cpu, _ = this_cpu()
    host = host_name()
    kept = workspace.peak(digest([host, cpu.model, threads]))
    held = json.loads(kept.read_text()) if kept.is_file() else None
    if held and (not held.get("machine_disturbed") or held.get("machine_measurements", 1) >= ATTEMPTS):
        return held
    phase(f"peak · {threads} thread(s)")
    begin = read_counts()
    try:
        peak = measure(threads, ort_kernels(threads, cpu.flags))
    except Exception as exc:  # any: no ONNX Runtime here, or a kernel that failed: the profile holds without
        return held or {"machine_reason": f"the machine's peak could not be measured: {type(exc).__name__}: "
                                          f"{exc}"}
    fields = {**peak.fields(), "machine_host": host, "machine_cpu": cpu.model,
              "machine_measured_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine_disturbed": between(begin, read_counts()).problem(LIMITS), "machine_measurements": 1}
    fields = best_of(held, fields) if held else fields
    partial = workspace.partial(kept)
    partial.write_text(json.dumps(fields))
    partial.replace(kept)  # a reader never sees a half-written peak
    return fields
