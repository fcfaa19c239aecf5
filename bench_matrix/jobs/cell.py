"""A cell's own jobs: convert its source into its artifact, then load, time and evaluate that artifact."""

from __future__ import annotations

import hashlib
import resource
import time
from typing import Any

import numpy as np

from bench_matrix import data, hardware
from bench_matrix.backends.registry import load_backend
from bench_matrix.jobs import ConvertJob, MeasureJob
from bench_matrix.jobs.artifact import ensure_artifact, predict_all
from bench_matrix.measure import env as environment
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measure.metrics import evaluate, non_finite_reason
from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import latency_summary
from bench_matrix.measure.timing import LoopSettings, steady_time_calls, throughput
from bench_matrix.tensors import bind, resize, take
from bench_matrix.worker import phase

LATENCY_INPUTS = 16
GPU_TARGETS = ("cuda", "tensorrt")  # timed compute-only and end to end; GPU name and memory recorded


class NonFiniteOutputs(Exception):
    """The cell's outputs hold NaN or Inf: a failure, never a result."""


def convert(job: ConvertJob) -> dict[str, Any]:
    phase("convert")
    artifact, manifest, cached = ensure_artifact(
        job.workspace, load_backend(job.cell.backend), job.source, job.step, job.cell.precision, job.cell.target,
        job.data, job.layout, job.settings, job.options)
    return {"artifact_dir": str(artifact), "manifest": manifest, "cached": cached}


def measure(job: MeasureJob) -> dict[str, Any]:
    """Load, time at batch 1, time throughput, record peak memory, then evaluate the outputs."""
    cell, settings, prepared = job.cell, job.settings, job.data
    backend = load_backend(cell.backend)
    few, _ = data.load_split(prepared.directory, "test", prepared.preprocess, job.layout,
                             max(LATENCY_INPUTS, settings.batch_size))
    few = bind(few, job.source.inputs)
    on_gpu = cell.target in GPU_TARGETS
    gpu_memory = GpuMemory() if on_gpu else None  # before the load: the fallback reading subtracts this
    phase("load")
    begin = time.perf_counter()
    session = backend.load(job.artifact_dir / "model", job.manifest["meta"], cell.target, cell.precision,
                           settings.threads)
    load_s = time.perf_counter() - begin
    hosts = [take(few, slice(i, i + 1)) for i in range(min(LATENCY_INPUTS, len(next(iter(few.values())))))]
    singles = [session.prepare(h) for h in hosts]
    batch = session.prepare(resize(few, settings.batch_size))
    loop = LoopSettings(settings.warmup_iterations, settings.warmup_s, settings.min_iterations,
                        settings.min_time_s, settings.max_time_s)
    phase("measure")
    durations, stability = steady_time_calls(session.execute, singles, loop)
    gpu: dict[str, Any] = {}
    if on_gpu:  # end to end: from host arrays, both copies and fetch inside the clock
        gpu["latency_ms_e2e"] = latency_summary(steady_time_calls(session.predict, hosts, loop)[0])
    rate = throughput(session.execute, batch, settings.batch_size, settings.throughput_time_s)
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    phase("evaluate")
    x, y = data.load_split(prepared.directory, "test", prepared.preprocess, job.layout, settings.eval_samples)
    outputs = predict_all(session, bind(x, job.source.inputs), settings.batch_size)
    if reason := non_finite_reason(outputs):
        raise NonFiniteOutputs(f"the cell's outputs on the test split are not finite: {reason}")
    if gpu_memory is not None:
        gpu.update(gpu_name=hardware.gpus()[0].name if hardware.gpus() else None, **gpu_memory.peak())
    reference = _reference(job)
    metrics = {**artifact_size(job.artifact_dir / "model", job.artifact_dir / "size.json"),
               "params": job.manifest["params"], **evaluate(job.task, outputs, y, reference, job.metrics),
               "outputs_sha256": outputs_digest(outputs), "latency_ms": latency_summary(durations), **gpu,
               **stability, **rate, "batch_size": settings.batch_size, "peak_rss_mb": round(peak_rss_mb, 1),
               "convert_s": job.manifest["convert_s"], "load_s": load_s, "threads": settings.threads,
               "artifact_cached": job.cached, "session": session.info(), "test_samples": int(len(outputs[0])),
               **_finetune_metrics(job.finetune, job.manifest["convert_s"])}
    return {"metrics": metrics, "env": {**environment.capture(), "backend_versions": backend.versions(),
                                        "runtime": session.info()}}


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
