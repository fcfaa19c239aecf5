"""The latency scenario, the core one (base.CORE): the loaded session timed at batch 1 (and end to end on a
GPU) and at the throughput batch in the windows of interleaved rounds (the executor owns the clock:
docs/metrics.md §5), then its outputs evaluated; the timed figures are made from the rounds' windows."""

from __future__ import annotations

import hashlib
import resource
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench_matrix import data, hardware
from bench_matrix.jobs import MeasureJob
from bench_matrix.jobs.artifact import predict_all
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measure.interference import LIMITS, Sampler
from bench_matrix.measure.metrics import evaluate, non_finite_reason
from bench_matrix.measure.schedule import LATENCY, Window
from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.timing import WINDOW_WARMUP, LoopSettings, latency_window, time_calls
from bench_matrix.phases import phase
from bench_matrix.scenarios.base import Loaded, Outcome, Scenario
from bench_matrix.scenarios.timed import E2E, THROUGHPUT
from bench_matrix.tensors import bind, resize, take

LATENCY_INPUTS = 16
SHARE = {THROUGHPUT: 0.5}  # of settings.window_s: throughput's figures need fewer calls than the p50's
WARMUP = {THROUGHPUT: 1}  # calls before a window: one batch warms up as the latency window's 2 calls do


class NonFiniteOutputs(Exception):
    """The cell's outputs hold NaN or Inf: a failure, never a result."""


@dataclass(frozen=True)
class Timer:
    """A loaded cell's timed calls: for each kind of window, the call, its inputs and the samples a call
    carries (1, or the throughput batch)."""

    calls: dict[str, tuple[Callable[[Any], Any], list[Any], int]]

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.calls)

    def window(self, kind: str, seconds: float) -> Window:
        """Time one window of `kind` now (throughput: half as long), with the interference during it."""
        call, inputs, samples = self.calls[kind]
        sampler = Sampler()
        durations_ns = latency_window(call, inputs, seconds * SHARE.get(kind, 1.0), sampler,
                                      warmup=WARMUP.get(kind, WINDOW_WARMUP))
        interference = sampler.stop()
        return Window(kind, durations_ns / 1e6, samples, interference.problem(LIMITS), interference.as_dict())


class Latency(Scenario):
    """The core scenario: the session timed in the rounds' windows, and evaluated."""

    name = "latency"

    def timer(self, loaded: Loaded) -> Timer:
        """The cell's inputs prepared for the session (batch 1 from the test split, and the throughput batch),
        and every kind of window warmed up once (settings.warmup_iterations and warmup_s)."""
        job, session, settings = loaded.job, loaded.session, loaded.job.settings
        few, _ = data.load_split(job.data.directory, "test", job.data.preprocess, job.layout,
                                 max(LATENCY_INPUTS, settings.batch_size))
        few = bind(few, job.source.inputs)
        hosts = [take(few, slice(i, i + 1))
                 for i in range(min(LATENCY_INPUTS, len(next(iter(few.values())))))]
        calls = {LATENCY: (session.execute, [session.prepare(h) for h in hosts], 1)}
        if loaded.on_gpu:  # end to end: from host arrays, both copies and fetch inside the clock
            calls[E2E] = (session.predict, hosts, 1)
        calls[THROUGHPUT] = (session.execute, [session.prepare(resize(few, settings.batch_size))],
                             settings.batch_size)
        phase("warm-up")
        warm = LoopSettings(settings.warmup_iterations, settings.warmup_s, 1, 0.0, settings.warmup_s)
        for call, inputs, _ in calls.values():
            time_calls(call, inputs, warm)
        return Timer(calls)

    def evaluate(self, loaded: Loaded, before: Outcome | None = None) -> Outcome:
        """What the cell's record holds besides its timed figures: size, accuracy, memory, load, the session's
        facts; when evaluated `before` the rounds, the peak memory read again (their batches may raise it)."""
        if before is not None:
            peak_rss_mb = max(before.fields["peak_rss_mb"], _peak_rss_mb())
            return Outcome({**before.fields, "peak_rss_mb": peak_rss_mb}, before.samples)
        job, session, settings = loaded.job, loaded.session, loaded.job.settings
        peak_rss_mb = _peak_rss_mb()
        phase("evaluate")
        accuracy, outputs = _evaluate(job, session)
        converted, manifest = job.converted, job.converted.manifest
        kept = converted.directory / "size.json"
        metrics = {**artifact_size(converted.model, kept, job.workspace.partial(kept)),
                   "params": manifest["params"], **accuracy, "outputs_sha256": outputs_digest(outputs),
                   "cpu_affinity": loaded.cpus, **_gpu_metrics(loaded.gpu_memory),
                   "batch_size": settings.batch_size,
                   "peak_rss_mb": peak_rss_mb, "convert_s": manifest["convert_s"],
                   "load_s": loaded.load_s,
                   "threads": settings.threads, "artifact_cached": converted.cached,
                   "session": session.info(), "test_samples": int(len(outputs[0])),
                   **_finetune_metrics(job.finetune, manifest["convert_s"])}
        if manifest.get("calibration"):  # how many calibration samples were asked for and used
            metrics["calibration"] = manifest["calibration"]
        return Outcome(metrics)


def _peak_rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


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


def _reference(job: MeasureJob) -> list[np.ndarray] | None:
    """The fp32 baseline's outputs on the same test samples, in output order."""
    if job.reference is None:
        return None
    with np.load(job.reference) as kept:
        return [kept[f"arr_{i}"] for i in range(len(kept.files))]


def _finetune_metrics(facts: dict[str, Any] | None, convert_s: float) -> dict[str, Any]:
    """For a fine-tuned model: convert_s including the fine-tuning, finetune_s, sparsity, clusters (when it
    was clustered: elsewhere the most distinct values per kernel is just its size), the facts."""
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
