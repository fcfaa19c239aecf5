"""The latency scenario, run first by every measure job: the loaded session timed at batch 1 (and end to end
on a GPU) and at throughput, then its outputs evaluated."""

from __future__ import annotations

import hashlib
import resource
from typing import Any

import numpy as np

from bench_matrix import data, hardware
from bench_matrix.phases import phase, waiting
from bench_matrix.jobs import MeasureJob
from bench_matrix.jobs.artifact import predict_all
from bench_matrix.matrix.spec import Settings
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measure.interference import Limits
from bench_matrix.measure.machine_lock import timing_slot
from bench_matrix.measure.metrics import evaluate, non_finite_reason
from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import latency_summary, pack_samples
from bench_matrix.measure.timing import (
    LoopSettings,
    Phase,
    drift,
    interference_record,
    steady_throughput,
    steady_time_calls,
)
from bench_matrix.scenarios.base import Loaded, Outcome
from bench_matrix.tensors import bind, resize, take

LATENCY_INPUTS = 16
LIMITS = Limits()  # interference above these re-measures a timed phase, then flags the cell
# stored raw series: the timed phase and the key of its durations (ns) in that phase's result ("" = the result)
SAMPLED = {"latency_ms": ("latency", ""), "latency_ms_e2e": ("latency_e2e", ""),
           "batch_ms": ("throughput", "batch_ns")}


class NonFiniteOutputs(Exception):
    """The cell's outputs hold NaN or Inf: a failure, never a result."""


def run(loaded: Loaded) -> Outcome:
    """Time at batch 1 and throughput holding the machine's timing slot, record peak memory, then evaluate the
    outputs; the raw latencies come back packed."""
    job, session, settings = loaded.job, loaded.session, loaded.job.settings
    few, _ = data.load_split(job.data.directory, "test", job.data.preprocess, job.layout,
                             max(LATENCY_INPUTS, settings.batch_size))
    few = bind(few, job.source.inputs)
    hosts = [take(few, slice(i, i + 1)) for i in range(min(LATENCY_INPUTS, len(next(iter(few.values())))))]
    singles = [session.prepare(h) for h in hosts]
    batch = session.prepare(resize(few, settings.batch_size))
    cell = job.cell
    with timing_slot(f"{job.workspace.root} · {cell.model} · {cell.label}", on_wait=waiting) as window:
        phase("measure")
        phases = timed_phases(session, singles, hosts, batch, settings, loaded.on_gpu)
    timing = {**_timing_metrics(phases), "timing_window": window.as_dict(), "cpu_affinity": loaded.cpus}
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    phase("evaluate")
    accuracy, outputs = _evaluate(job, session)
    converted, manifest = job.converted, job.converted.manifest
    metrics = {**artifact_size(converted.model, converted.directory / "size.json"),
               "params": manifest["params"], **accuracy, "outputs_sha256": outputs_digest(outputs), **timing,
               **_gpu_metrics(loaded.gpu_memory), "batch_size": settings.batch_size,
               "peak_rss_mb": round(peak_rss_mb, 1), "convert_s": manifest["convert_s"],
               "load_s": loaded.load_s,
               "threads": settings.threads, "artifact_cached": converted.cached, "session": session.info(),
               "test_samples": int(len(outputs[0])), **_finetune_metrics(job.finetune, manifest["convert_s"])}
    if manifest.get("calibration"):  # how many calibration samples were asked for and used
        metrics["calibration"] = manifest["calibration"]
    return Outcome(metrics, _packed(phases))


def _evaluate(job: MeasureJob, session: Any) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The accuracy metrics on the test split (against the labels and the baseline's outputs) and the
    outputs; NonFiniteOutputs when they hold NaN or Inf."""
    prepared, settings = job.data, job.settings
    x, y = data.load_split(prepared.directory, "test", prepared.preprocess, job.layout, settings.eval_samples)
    outputs = predict_all(session, bind(x, job.source.inputs), settings.batch_size)
    if reason := non_finite_reason(outputs):
        raise NonFiniteOutputs(f"the cell's outputs on the test split are not finite: {reason}")
    return evaluate(job.task, outputs, y, _reference(job), job.metrics), outputs


def _gpu_metrics(gpu_memory: GpuMemory | None) -> dict[str, Any]:
    """On a GPU: its name and the cell's peak GPU memory."""
    if gpu_memory is None:
        return {}
    return {"gpu_name": hardware.gpus()[0].name if hardware.gpus() else None, **gpu_memory.peak()}


def timed_phases(session: Any, singles: list[Any], hosts: list[Any], batch: Any, settings: Settings,
                  on_gpu: bool) -> dict[str, Phase[Any]]:
    """Latency at batch 1 (and end to end on a GPU), then throughput; each re-measured while disturbed."""
    loop = LoopSettings(settings.warmup_iterations, settings.warmup_s, settings.min_iterations,
                        settings.min_time_s, settings.max_time_s, settings.ci_rel_width)
    phases: dict[str, Phase[Any]] = {"latency": steady_time_calls(session.execute, singles, loop, LIMITS)}
    if on_gpu:  # end to end: from host arrays, both copies and fetch inside the clock
        phases["latency_e2e"] = steady_time_calls(session.predict, hosts, loop, LIMITS)
    phases["throughput"] = steady_throughput(session.execute, batch, settings.batch_size,
                                             settings.throughput_time_s, LIMITS)
    return phases


def _timing_metrics(phases: dict[str, Phase[Any]]) -> dict[str, Any]:
    """The latency statistics (with their confidence intervals), throughput and the interference record."""
    latency = phases["latency"]
    timing = {"latency_ms": latency_summary(latency.result),
              "latency_stability": round(drift(latency.result), 4), "latency_attempts": len(latency.attempts),
              **{k: v for k, v in phases["throughput"].result.items() if k != "batch_ns"},
              "interference": interference_record(phases, LIMITS)}
    if "latency_e2e" in phases:
        timing["latency_ms_e2e"] = latency_summary(phases["latency_e2e"].result)
    return timing


def _packed(phases: dict[str, Phase[Any]]) -> dict[str, bytes]:
    """The kept raw durations of each sampled series, packed (stats.pack_samples)."""
    return {name: pack_samples(phases[timed].result[key] if key else phases[timed].result)
            for name, (timed, key) in SAMPLED.items() if timed in phases}


def _reference(job: MeasureJob) -> list[np.ndarray] | None:
    """The fp32 baseline's outputs on the same test samples, in output order."""
    if job.reference is None:
        return None
    with np.load(job.reference) as kept:
        return [kept[f"arr_{i}"] for i in range(len(kept.files))]


def _finetune_metrics(facts: dict[str, Any] | None, convert_s: float) -> dict[str, Any]:
    """For a fine-tuned model: convert_s including the fine-tuning, finetune_s, sparsity, clusters (when it was
    clustered: elsewhere the most distinct values per kernel is just its size), the facts."""
    if not facts:
        return {}
    clusters = facts.get("clusters") if "target_clusters" in facts else None
    return {"convert_s": convert_s + facts["finetune_s"], "finetune_s": facts["finetune_s"],
            "sparsity": facts.get("sparsity"), "clusters": clusters, "finetune": facts}


def outputs_digest(outputs: list[np.ndarray]) -> str:
    """SHA-256 of every output as contiguous float32: equal only for bit-identical outputs."""
    h = hashlib.sha256()
    for out in outputs:
        h.update(np.ascontiguousarray(out, dtype=np.float32).tobytes())
    return h.hexdigest()
