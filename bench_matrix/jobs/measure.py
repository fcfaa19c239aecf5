"""The measure job: load a cell's artifact once and keep it, serving timed windows of the executor's rounds
(the core scenarios' timers); then evaluate it and run the cell's planned scenarios with the loaded session
(bench_matrix/scenarios)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from bench_matrix.cell import Planned
from bench_matrix.jobs import MeasureJob
from bench_matrix.jobs.results import Measured
from bench_matrix.measure import env as environment
from bench_matrix.measure.affinity import pin_threads
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measure.schedule import Window
from bench_matrix.measurement import Measurement
from bench_matrix.named import resolve
from bench_matrix.phases import phase
from bench_matrix.registry import load_backend
from bench_matrix.scenarios.base import CORE, Loaded, Outcome, Scenario, Windows


@dataclass
class Served:
    """A cell's loaded session kept alive in its process: evaluated, windows on demand, then `finish`."""

    loaded: Loaded
    core: tuple[Scenario, ...]
    timers: dict[str, Windows]  # each kind of window -> the core scenario's timer serving it
    evaluated: tuple[Outcome, ...] | None = None

    def evaluate(self) -> dict[str, Any]:
        """Evaluate the session (before its rounds): what its record holds besides the timed figures."""
        self.evaluated = tuple(scenario.evaluate(self.loaded) for scenario in self.core)
        return {k: v for outcome in self.evaluated for k, v in outcome.fields.items()}

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.timers)

    def window(self, kind: str, seconds: float) -> Window:
        return self.timers[kind].window(kind, seconds)

    def finish(self) -> Measured:
        """Evaluate the session unless it was (brought up to date now), then run each planned scenario in
        order; the timed figures are the executor's to add."""
        loaded, before = self.loaded, self.evaluated or (None,) * len(self.core)
        evaluated = (scenario.evaluate(loaded, early) for scenario, early in zip(self.core, before))
        outcomes = [*evaluated, *(_run(planned, loaded) for planned in loaded.job.scenarios)]
        metrics = Measurement.from_json({k: v for outcome in outcomes for k, v in outcome.fields.items()})
        samples = {k: v for outcome in outcomes for k, v in outcome.samples.items()}
        env = {**environment.capture(), "backend_versions": loaded.backend.versions(),
               "runtime": loaded.session.info()}
        return Measured(metrics, samples, env)


def open_session(job: MeasureJob) -> Served:
    """Load the cell's artifact, then have each core scenario prepare its inputs and warm its windows up."""
    loaded, scenarios = load(job), tuple(resolve(name)() for name in CORE)
    timers = {kind: timer for timer in (scenario.timer(loaded) for scenario in scenarios) if timer
              for kind in timer.kinds}
    return Served(loaded, scenarios, timers)


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
