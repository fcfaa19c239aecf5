"""The probe job: describe each backend, rule on every combination and fine-tuning, read model files' inputs
and the parameters of factories' forward."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bench_matrix.backend import Backend
from bench_matrix.jobs import ProbeJob
from bench_matrix.jobs.results import Probe
from bench_matrix.cell import TrainingKey, Ruling
from bench_matrix.strategy import StrategySpec
from bench_matrix.registry import BackendLoadError, load_backend
from bench_matrix.sources.forward_call import Parameter
from bench_matrix.sources.model_io import FileInputs, read_file

DEFAULT_FORMAT = {"pytorch": "state_dict", "tensorflow": "keras"}  # what built-in models arrive as


def probe(job: ProbeJob) -> Probe:
    """Backends described, rulings per combination, trainers per fine-tuning, inputs per model file,
    forward's parameters per factory."""
    backends, described = _load(job.backends)
    keys = job.keys if job.keys is not None else _declared(backends)
    trainers = {key: Ruling() for key in job.training} if job.measure_only else rule_training(job.training)
    rulings = {key: _ruling(backends, described, _converted(key, trainers), job.measure_only)
                for key in keys}
    files = {path: _read(framework, fmt, path) for framework, fmt, path in job.model_files}
    return Probe(described, rulings, trainers,
                 inputs={path: read and read.inputs for path, read in files.items()},
                 forwards={factory: _forward(factory, path) for factory, path in job.factories},
                 batches={path: read.fixed_batch for path, read in files.items() if read})


def _load(names: tuple[str, ...]) -> tuple[dict[str, Backend | None], dict[str, Any]]:
    backends: dict[str, Backend | None] = {}
    described: dict[str, Any] = {}
    for name in names:
        try:
            b = load_backend(name)
        except BackendLoadError as exc:
            backends[name], described[name] = None, {"error": str(exc)}
            continue
        backends[name] = b
        described[name] = {"error": None, "description": b.description, "versions": b.versions(),
                           "baseline_for": list(b.baseline_for), "slow_start": b.slow_start,
                           "supports": [{k: list(getattr(s, k)) for k in ("frameworks", "strategies",
                                         "precisions", "targets")} for s in b.supports],
                           "devices": {t: b.device(t) for s in b.supports for t in s.targets}}
    return backends, described


def _declared(backends: dict[str, Backend | None]) -> list[tuple]:
    """Every combination the loaded backends declare, for a default source of each framework."""
    return [(n, f, st, p, t, DEFAULT_FORMAT.get(f, f), "{}", "") for n, b in backends.items() if b
            for s in b.supports for f in s.frameworks for st in s.strategies for p in s.precisions
            for t in s.targets]


def _converted(key: tuple, trainers: dict[TrainingKey, Ruling]) -> tuple:
    """The key with the format the backend will really convert: after a fine-tuning, the trainer's output."""
    *head, source_format, options, training = key
    ruled = trainers.get(tuple(json.loads(training))) if training else None
    return (*head, (ruled and ruled.format) or source_format, options)


def _ruling(backends: dict[str, Backend | None], described: dict[str, Any], key: tuple, measure_only: bool
             ) -> Ruling:
    """Whether the backend implements the combination and can run it here (and, unless `measure_only`, read
    and convert its source here)."""
    name, framework, kind, precision, target, source_format, options = key
    b = backends[name]
    if b is None:
        return Ruling(skip=described[name]["error"])
    step = StrategySpec(name=kind, kind=kind, options=json.loads(options))
    invalid = b.invalid_reason(framework, kind, precision, target) or b.option_reason(step, source_format)
    try:
        reasons = [] if invalid else [b.probe(target, precision)]
        if not (invalid or measure_only):
            reasons += [b.probe_source(framework, source_format),
                        b.convert_needs_reason(framework, kind, precision, target)]
        skip = "; ".join(r for r in reasons if r) or None
    except Exception as exc:  # a probe that crashes is a reason, not a crash of the run
        skip = f"probing {name} for {target}/{precision} failed: {type(exc).__name__}: {exc}"
    return Ruling(invalid, skip)


def rule_training(keys: tuple[TrainingKey, ...]) -> dict[TrainingKey, Ruling]:
    """For each (framework, source format, steps, task) the first installed trainer that can apply it, or why
    none can."""
    from bench_matrix.strategies.registry import TrainerLoadError, load_trainer, trainer_names

    trainers, errors = [], []
    for name in trainer_names():
        try:
            trainers.append(load_trainer(name))
        except TrainerLoadError as exc:
            errors.append(str(exc))
    rulings = {}
    for framework, source_format, steps_json, task in keys:
        steps = tuple(StrategySpec.from_dict(s) for s in json.loads(steps_json))
        kinds = ", ".join(s.kind or "" for s in steps)
        ruled = [(t, t.steps_reason(steps, source_format, task)) for t in trainers
                 if t.framework == framework]
        able = [t for t, r in ruled if not r]
        key = (framework, source_format, steps_json, task)
        if not able:
            why = "; ".join([f"{t.name}: {r}" for t, r in ruled if r] + errors)
            why = why or f"no installed trainer fine-tunes {framework} models"
            rulings[key] = Ruling(invalid=f"{kinds}: {why}")
            continue
        try:
            skip = able[0].probe()
        except Exception as exc:  # a probe that crashes is a reason, not a crash of the run
            skip = f"probing trainer {able[0].name} failed: {type(exc).__name__}: {exc}"
        written = able[0].output_format(steps, source_format)
        rulings[key] = Ruling(skip=skip, by=able[0].name, format=written)
    return rulings


def _read(framework: str, source_format: str, path: str) -> FileInputs | None:
    """The inputs and fixed batch sizes a model file declares; None when it does not say or cannot be read."""
    try:
        return read_file(framework, source_format, Path(path))
    except Exception:  # a file we cannot read is the model's failure, reported when it is prepared
        return None


def _forward(factory: str, python_path: tuple[str, ...]) -> tuple[Parameter, ...] | None:
    """The parameters of forward of the module the factory builds; None when it cannot be built."""
    from bench_matrix.sources.forward_call import forward_parameters
    from bench_matrix.sources.pytorch import build_from_factory

    try:
        return tuple(forward_parameters(build_from_factory(factory, python_path)))
    except Exception:  # the model's failure (torch missing included), reported when the model is prepared
        return None
