"""Pure functions turning stored records and facts into per-model rows, counts and the environment."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from bench_matrix.measure.affinity import NOT_EXPOSED
from bench_matrix.measure.metrics import HEADLINE
from bench_matrix.measurement import Measurement
from bench_matrix.report.analysis.plausible import implausible
from bench_matrix.report.analysis.reruns import Rerun, reruns
from bench_matrix.store import CellRecord

if TYPE_CHECKING:
    from bench_matrix.matrix.requirements import Requirements
    from bench_matrix.report.analysis.recommend import Recommendation
    from bench_matrix.verdict import Verdict

STATUSES = ("ok", "skipped", "failed")
# (label, env key) of the hardware/software fields shown in environment blocks, in display order.
ENV_FIELDS = (("Host", "host"), ("OS", "os"), ("CPU", "cpu"), ("Architecture", "arch"),
              ("CPU features", "cpu_features"), ("Emulated", "emulated"), ("Cores", "cores"),
              ("Memory GB", "memory_gb"), ("CPU frequency", "cpu_frequency"), ("GPUs", "gpus"),
              ("Python", "python"), ("bench-matrix", "bench_matrix"))

DRIFT_LIMIT = 0.05  # records from before the rounds: chunk medians of the latency drifted by more (unsteady)


@dataclass(frozen=True)
class Row:
    """An ok cell compared with its model's baseline; a comparison is None where either side lacks the metric."""

    record: CellRecord
    is_baseline: bool
    speedup: float | None
    size_ratio: float | None
    mse_delta: float | None
    speedup_own_fp32: float | None = None  # vs the same backend's fp32 cell (strategy none, same target)
    speedup_half: float | None = None  # the paired speed-up's 95 % interval, its larger side relative
    accuracy_delta: float | None = None  # the task's headline metric (HEADLINE) minus the baseline's
    verdict: Verdict | None = None  # against the model's requirements (judging.py); None: none given


@dataclass(frozen=True)
class Environment:
    """Distinct values of each environment field over a set of records; `warnings` name those that differ."""

    fields: tuple[tuple[str, tuple[str, ...]], ...]
    libraries: tuple[tuple[str, tuple[str, ...]], ...]
    runtime: tuple[tuple[str, tuple[str, ...]], ...]
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class ModelSummary:
    """Everything the report shows for one model."""

    name: str
    framework: str
    info: dict[str, Any]
    baseline_key: str
    baseline: CellRecord | None
    rows: tuple[Row, ...]
    skipped: tuple[CellRecord, ...]
    failed: tuple[CellRecord, ...]
    environment: Environment
    suspects: tuple[str, ...] = ()  # cells at different precisions whose test outputs are bit-identical
    implausible: Mapping[str, str] = field(default_factory=dict)  # why each cell's record cannot be right
    disturbed: tuple[str, ...] = ()  # cells flagged for interference (every attempt of a phase), and why
    wide: tuple[str, ...] = ()  # cells whose latency interval missed the ci_target asked for (older: drifted)
    requirements: Requirements | None = None  # what its cells were judged against; None: nothing declared
    requirements_from: str = ""  # where they were read
    recommendations: tuple[Recommendation, ...] = ()  # per target (and host) its cells ran on
    reruns: tuple[Rerun, ...] = ()  # other runs that timed its shown artifacts on their hosts
    # what accuracy is compared with (ΔMSE, max_drop): the baseline's ok record's figures, else its test
    # metrics from where the model was prepared when every ok cell scored as many samples (a device without
    # the baseline's runtime); None: neither
    accuracy_baseline: Measurement | None = None

    @property
    def task(self) -> str:
        return task_of(self.info)

    @property
    def implausible_lines(self) -> tuple[str, ...]:
        """One line per ok cell whose record cannot be right: the cell and why (its verdict fails on it)."""
        labels = {row.record.cell.key: row.record.cell.label for row in self.rows}
        return tuple(f"{labels.get(key, key)}: {why}; it is never recommended"
                     for key, why in sorted(self.implausible.items()))

    @property
    def best(self) -> Row | None:
        """The ok cell with the lowest p50 latency, if any cell has one."""
        timed = [r for r in self.rows if p50(r.record) is not None]
        return min(timed, key=lambda r: (p50(r.record), r.record.cell.key)) if timed else None

    @property
    def batch_sizes(self) -> tuple[int, ...]:
        return _distinct_metric(self.rows, lambda m: m.throughput.batch_size)

    @property
    def threads(self) -> tuple[int, ...]:
        return _distinct_metric(self.rows, lambda m: m.setup.threads)


@dataclass(frozen=True)
class Report:
    """The whole store, summarised: models in name order, the union environment, the last run and counts."""

    models: tuple[ModelSummary, ...]
    environment: Environment
    run: dict[str, Any]
    counts: dict[str, int]


def number(value: Any) -> float | None:
    """The value as a float when it is a real number (bools and text are not), else None."""
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def metric(record: CellRecord, key: str) -> float | None:
    """A numeric metric by its record key (a task metric, a plugin's NAME.FIGURE), or None when absent or
    malformed."""
    return number(record.metrics.figure(key))


def figure(record: CellRecord, read: Callable[[Measurement], Any]) -> float | None:
    """A numeric figure read from the typed measurement (e.g. `lambda m: m.throughput.sps`), or None."""
    return number(read(record.metrics))


def p50(record: CellRecord) -> float | None:
    return figure(record, lambda m: m.latency and m.latency.p50)


def headline(text: str | None) -> str:
    """The first non-blank line of a reason (the error itself; the lines after it locate it), or ""."""
    lines = [line.strip() for line in (text or "").splitlines() if line.strip()]
    return lines[0] if lines else ""


def task_of(info: Mapping[str, Any]) -> str:
    """The model's task as its preparation recorded it; stores written before tasks existed: regression."""
    return str(info.get("task") or "regression")


def count(records: Iterable[CellRecord]) -> dict[str, int]:
    records = list(records)
    return {status: sum(r.status == status for r in records) for status in STATUSES}


def summarize(records: list[CellRecord], infos: Mapping[str, dict[str, Any]], run: dict[str, Any],
              history: Iterable[CellRecord] = ()) -> Report:
    """Group records by model and compare each ok cell with the model's baseline; `history`: ok records of
    the same cells from any run, for the moves between runs."""
    by_model: dict[str, list[CellRecord]] = {}
    for record in records:
        by_model.setdefault(record.cell.model, []).append(record)
    history = list(history)
    models = tuple(_model(name, by_model[name], infos.get(name) or {}, history) for name in sorted(by_model))
    return Report(models=models, environment=environment(records), run=run, counts=count(records))


def _model(name: str, records: list[CellRecord], info: dict[str, Any], history: list[CellRecord]
           ) -> ModelSummary:
    framework = info.get("framework") or records[0].cell.framework
    baseline_key = info.get("baseline_key", "")  # written when the model was prepared; absent: no comparison
    baseline = next((r for r in records if r.cell.key == baseline_key), None)
    reference = baseline if baseline is not None and baseline.status == "ok" else None
    ok = [r for r in records if r.status == "ok"]
    ok.sort(key=lambda r: (r is not reference, p50(r) is None, p50(r) or 0.0, r.cell.key))
    own_fp32 = {(r.cell.backend, r.cell.target): r for r in ok
                if r.cell.strategy == "none" and r.cell.precision == "fp32"}
    headline_metric = HEADLINE.get(task_of(info), "")
    accuracy = reference.metrics if reference is not None else prepared_baseline(info, ok)
    rows = tuple(_row(r, reference, own_fp32.get((r.cell.backend, r.cell.target)), headline_metric, accuracy)
                 for r in ok)
    by_key = sorted(records, key=lambda r: r.cell.key)
    return ModelSummary(name=name, framework=framework, info=info, baseline_key=baseline_key, baseline=baseline,
                        rows=rows, skipped=tuple(r for r in by_key if r.status == "skipped"),
                        failed=tuple(r for r in by_key if r.status == "failed"), environment=environment(records),
                        suspects=suspects(ok), implausible=implausible(ok),
                        disturbed=problem_lines(ok, disturbed_phases),
                        wide=problem_lines(ok, wide_phases),
                        reruns=reruns(ok, (r for r in history if r.cell.model == name)),
                        accuracy_baseline=accuracy)


def prepared_baseline(info: Mapping[str, Any], ok: list[CellRecord]) -> Measurement | None:
    """The baseline's test metrics from where the model was prepared, when every ok cell scored as many test
    samples (the fp32 outputs their max |Δ| is taken against); else None."""
    metrics, samples = info.get("test_metrics"), info.get("test_samples")
    scored = {record.metrics.figure("test_samples") for record in ok}
    if isinstance(metrics, dict) and isinstance(samples, int) and scored == {samples}:
        return Measurement.from_json({**metrics, "test_samples": samples})
    return None


def emulated(record: CellRecord) -> str | None:
    """Why the record's timings are not its device's (measured on an emulated CPU: qemu-user), or None."""
    return (record.env or {}).get("emulated")


def disturbed_phases(record: CellRecord) -> dict[str, str]:
    """The timed phases (latency, latency_e2e, throughput) of a record flagged for interference: disturbed in
    every attempt, with why."""
    return _kept_problems(record, "disturbed")


def asked(record: CellRecord) -> bool | None:
    """Whether the user set the precision (`ci_target`) the record's rounds aimed at; None for records from
    before the rounds said so."""
    facts = record.metrics.rounds
    value = facts.to_json().get("asked") if facts is not None else None
    return value if isinstance(value, bool) else None


def wide_phases(record: CellRecord) -> dict[str, str]:
    """Timed phases whose interval stayed wider than the precision asked, with why (none if none asked); for
    pre-rounds records, those whose kept attempt drifted (by stability before interference was measured)."""
    if asked(record) is False:
        return {}
    if record.metrics.interference is not None:
        return _kept_problems(record, "wide")
    stability = figure(record, lambda m: m.passes.stability)
    return ({"latency": f"chunk medians drifted by {stability:.0%} (limit {DRIFT_LIMIT:.0%})"}
            if stability is not None and stability > DRIFT_LIMIT else {})


def _kept_problems(record: CellRecord, kind: str) -> dict[str, str]:
    """The `kind` ("disturbed" or "wide") text of each timed phase, where it has one; in records from before
    the rounds, that of the kept attempt ("wide" was "unsteady")."""
    interference = record.metrics.interference
    phases = interference.phases if interference is not None else None
    found = {}
    for name, phase in (phases if isinstance(phases, dict) else {}).items():
        if not isinstance(phase, dict):
            continue
        if "attempts" not in phase:  # the rounds: each phase says why it is marked
            if isinstance(text := phase.get(kind), str) and text:
                found[name] = text
            continue
        attempts, kept = phase.get("attempts"), phase.get("kept")
        if isinstance(attempts, list) and isinstance(kept, int) and 0 <= kept < len(attempts):
            old = {"wide": "unsteady"}.get(kind, kind)
            text = attempts[kept].get(old) if isinstance(attempts[kept], dict) else None
            if text:
                found[name] = f"{text} ({len(attempts)} attempts, none clean)"
    return found


def problem_lines(records: Iterable[CellRecord], phases_of: Callable[[CellRecord], dict[str, str]]
                  ) -> tuple[str, ...]:
    """One line per record with problems by `phases_of`: the cell, then each phase and why."""
    lines = []
    for record in sorted(records, key=lambda r: r.cell.key):
        phases = phases_of(record)
        if phases:
            reasons = " | ".join(f"{name}: {why}" for name, why in phases.items())
            lines.append(f"{record.cell.label}: {reasons}")
    return tuple(lines)


def suspects(records: Iterable[CellRecord]) -> tuple[str, ...]:
    """One line per group of cells whose test outputs are bit-identical (same `outputs_sha256`) although their
    precisions differ: a lower precision that changes no output bit was most likely never applied."""
    groups: dict[str, list[CellRecord]] = {}
    for record in records:
        digest = record.metrics.task.outputs_sha256
        if isinstance(digest, str):
            groups.setdefault(digest, []).append(record)
    lines = []
    for same in groups.values():
        precisions = sorted({r.cell.precision for r in same})
        if len(precisions) > 1:
            cells = ", ".join(sorted(r.cell.key for r in same))
            lines.append(f"outputs are bit-identical at {' and '.join(precisions)} ({cells}): the lower "
                         f"precision was most likely not applied; treat these cells as suspect")
    return tuple(sorted(lines))


def _row(record: CellRecord, reference: CellRecord | None, own_fp32: CellRecord | None, headline_metric: str,
         accuracy: Measurement | None) -> Row:
    own = _ratio(p50(own_fp32), p50(record)) if own_fp32 is not None else None
    deltas = {"mse_delta": _difference(record, accuracy, "mse"),
              "accuracy_delta": _difference(record, accuracy, headline_metric) if headline_metric else None}
    if reference is None:
        return Row(record, False, None, None, speedup_own_fp32=own, **deltas)
    return Row(record=record, is_baseline=record is reference,
               speedup=_paired(record, reference) or _ratio(p50(reference), p50(record)),
               speedup_half=_paired_half(record, reference),
               size_ratio=_ratio(*(figure(r, lambda m: m.size.bytes) for r in (reference, record))),
               speedup_own_fp32=own, **deltas)


def _paired(record: CellRecord, reference: CellRecord) -> float | None:
    """The cell's speed-up paired by round against the baseline it was timed with (docs/metrics.md §5)."""
    found = record.metrics.speedup
    return number(found.value) if found is not None and record is not reference else None


def _paired_half(record: CellRecord, reference: CellRecord) -> float | None:
    found = record.metrics.speedup
    return number(found.ci_half) if found is not None and record is not reference else None


def _difference(record: CellRecord, accuracy: Measurement | None, key: str) -> float | None:
    value, base = metric(record, key), number(accuracy.figure(key)) if accuracy is not None else None
    return None if value is None or base is None else value - base


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    return None if numerator is None or denominator is None or denominator <= 0 else numerator / denominator


def _distinct_metric(rows: Iterable[Row], read: Callable[[Measurement], Any]) -> tuple[int, ...]:
    values = {figure(r.record, read) for r in rows}
    return tuple(sorted(int(v) for v in values if v is not None))


def _frequency(state: dict[str, Any]) -> str:
    """The CPU frequency policy in one line (driver, governors, boost, Intel no_turbo) or that it is hidden."""
    governor = state.get("scaling_governor")
    if isinstance(governor, dict):
        governor = " / ".join(sorted(set(governor.values())))
    named = (("driver", state.get("scaling_driver")), ("governor", governor), ("boost", state.get("boost")),
             ("intel no_turbo", state.get("intel_no_turbo")))
    shown = [f"{name} {value}" for name, value in named if value and value != NOT_EXPOSED]
    return ", ".join(shown) or "not exposed by this machine"


def _text(value: Any) -> str:
    if isinstance(value, list | tuple):
        return ", ".join(_text(v) for v in value) if value else "none"
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return str(value)


def environment(records: Iterable[CellRecord]) -> Environment:
    """The union of the records' environments; missing values are ignored, differing ones are warned about."""
    fields: dict[str, set[str]] = {label: set() for label, _ in ENV_FIELDS}
    libraries: dict[str, set[str]] = {}
    runtime: dict[str, set[str]] = {}
    for record in records:
        env = record.env or {}
        for label, key in ENV_FIELDS:
            if env.get(key) is not None:
                fields[label].add(_frequency(env[key]) if key == "cpu_frequency" else _text(env[key]))
        # the tool's libraries and each backend's own (a plugin's included)
        for name, version in {**(env.get("libraries") or {}), **(env.get("backend_versions") or {})}.items():
            libraries.setdefault(name, set()).add(_text(version))
        for name, value in (env.get("runtime") or {}).items():
            runtime.setdefault(f"{record.cell.backend} {name}", set()).add(_text(value))
    warnings = [f"{label} differs between cells: {' / '.join(sorted(values))}"
                for label, values in fields.items() if len(values) > 1]
    mixed = [f"{name} ({', '.join(sorted(v))})" for name, v in sorted(libraries.items()) if len(v) > 1]
    if mixed:
        warnings.append(f"library versions differ between cells: {'; '.join(mixed)}")
    return Environment(fields=tuple((k, tuple(sorted(v))) for k, v in fields.items() if v),
                       libraries=tuple((k, tuple(sorted(v))) for k, v in sorted(libraries.items())),
                       runtime=tuple((k, tuple(sorted(v))) for k, v in sorted(runtime.items())),
                       warnings=tuple(warnings))
