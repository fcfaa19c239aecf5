"""The measure job: load a cell's artifact once, then run the latency scenario and the cell's planned
scenarios with the loaded session (bench_matrix/scenarios)."""

from __future__ import annotations

import time

from bench_matrix.phases import phase
from bench_matrix.cell import Planned
from bench_matrix.jobs import MeasureJob
from bench_matrix.jobs.results import Measured
from bench_matrix.measure import env as environment
from bench_matrix.measure.affinity import pin_threads
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measurement import Measurement
from bench_matrix.named import resolve
from bench_matrix.registry import load_backend
from bench_matrix.scenarios import latency
from bench_matrix.scenarios.base import Loaded, Outcome


def measure(job: MeasureJob) -> Measured:
    """Load the session, measure its latency, then each planned scenario in order, after every timed loop."""
    loaded = load(job)
    outcomes = [latency.run(loaded), *(_run(planned, loaded) for planned in job.scenarios)]
    metrics = Measurement.from_json({k: v for outcome in outcomes for k, v in outcome.fields.items()})
    samples = {k: v for outcome in outcomes for k, v in outcome.samples.items()}
    env = {**environment.capture(), "backend_versions": loaded.backend.versions(),
           "runtime": loaded.session.info()}
    return Measured(metrics, samples, env)


def load(job: MeasureJob) -> Loaded:
    """Pin the threads and load the cell's artifact; on a GPU, its memory is read before the load."""
    cell, settings, converted = job.cell, job.settings, job.converted
    backend = load_backend(cell.backend)
    on_gpu = backend.device(cell.target) == "cuda"  # timed compute-only and end to end; GPU name, memory kept
    gpu_memory = GpuMemory() if on_gpu else None  # before the load: the fallback reading subtracts this
    cpus = pin_threads(settings.threads)  # before the load, so the runtime's threads inherit the affinity
    phase("load")
    begin = time.perf_counter()
    session = backend.load(converted.model, converted.manifest["meta"], cell.target, cell.precision,
                           settings.threads)
    return Loaded(job, backend, session, time.perf_counter() - begin, on_gpu, gpu_memory, cpus)


def _run(planned: Planned, loaded: Loaded) -> Outcome:
    """Run one planned scenario through the function it names."""
    return resolve(planned.function)(loaded, planned)
