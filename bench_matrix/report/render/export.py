"""Machine-readable exports: every record as JSON, and one flat CSV row per cell."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from bench_matrix.measurement import LatencyStats
from bench_matrix.report.analysis.noise import noise
from bench_matrix.report.analysis.summary import Report, Row, disturbed_phases, headline, metric, number
from bench_matrix.report.render.columns import MIB
from bench_matrix.report.render.noise_line import noise_json
from bench_matrix.report.render.verdict_view import open_lines
from bench_matrix.store import CellRecord

CELL_COLUMNS = ("key", "model", "framework", "backend", "strategy", "precision", "target", "host", "run")
LATENCY_STATS = ("mean", "p50", "p90", "p99", "std", "min")
CSV_COLUMNS = (*CELL_COLUMNS, "status", "reason", "size_bytes", "size_mib", "size_gzip_bytes", "size_gzip_mib",
               "params", "mse", "mae", "max_abs_diff_vs_baseline", *(f"latency_{s}_ms" for s in LATENCY_STATS),
               "latency_n", "latency_p50_ci_low_ms", "latency_p50_ci_high_ms", "latency_attempts",
               "latency_stability",
               "latency_e2e_p50_ms", "latency_e2e_p50_ci_low_ms", "latency_e2e_p50_ci_high_ms",
               "throughput_sps", "batch_size", "peak_rss_mb", "peak_gpu_mem_mb", "gpu_name", "convert_s",
               "finetune_s", "sparsity", "clusters", "load_s", "threads", "outputs_sha256",
               "artifact_cached", "speedup_vs_baseline", "size_ratio_vs_baseline", "mse_delta_vs_baseline",
               "task", "top1", "top5", "top1_agreement", "cosine_similarity", "snr_db",
               "accuracy_delta_vs_baseline", "interference_flagged", "interference_reason", "verdict",
               "verdict_missed")


def report_json(records: list[CellRecord], report: Report) -> str:
    """The JSON report: requirements, recommendations, open answers, machine noise (`noise`; null without
    window spreads), other runs' artifact p50s (`reruns`), records (to_json, store order) with verdicts."""
    verdicts = {_identity(row.record): row.verdict for model in report.models for row in model.rows}
    found = []
    for record in records:
        verdict = verdicts.get(_identity(record))
        found.append({**record.to_json(), **({"verdict": verdict.to_json()} if verdict else {})})
    required = {m.name: {"from": m.requirements_from, "requirements": dict(m.requirements.data)}
                for m in report.models if m.requirements is not None}
    recommended = [r.to_json() for model in report.models for r in model.recommendations]
    reruns = {m.name: [r.to_json() for r in m.reruns] for m in report.models if m.reruns}
    found_noise = noise(report)
    data = {"requirements": required, "recommendations": recommended, "open": open_lines(report.models),
            "noise": noise_json(found_noise) if found_noise is not None else None, "reruns": reruns,
            "records": found}
    return json.dumps(data, indent=2) + "\n"


def _identity(record: CellRecord) -> tuple[int | None, str, str | None]:
    return record.id, record.cell.key, record.host


def write_csv(records: list[CellRecord], report: Report, path: Path) -> Path:
    """Write one row per record (missing values empty) to `path` and return it."""
    rows = {_identity(row.record): row for model in report.models for row in model.rows}
    tasks = {model.name: model.task for model in report.models}
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for record in records:
            writer.writerow(csv_row(record, rows.get(_identity(record)), tasks.get(record.cell.model, "")))
    return path


def csv_row(record: CellRecord, row: Row | None, task: str) -> dict[str, Any]:
    """The flat CSV fields of one record of a model of `task`; `row` carries the baseline comparisons of an ok
    cell."""
    out: dict[str, Any] = {"key": record.cell.key, **record.cell.as_dict(), "host": record.host or "",
                           "run": record.run_id or "", "status": record.status,
                           "reason": headline(record.reason), "task": task}
    for name in ("size_bytes", "size_gzip_bytes", "params", "mse", "mae", "max_abs_diff_vs_baseline",
                 "throughput_sps", "batch_size", "peak_rss_mb", "peak_gpu_mem_mb", "convert_s", "finetune_s",
                 "sparsity", "clusters", "load_s", "threads", "top1", "top5", "top1_agreement",
                 "cosine_similarity", "snr_db"):
        out[name] = _plain(metric(record, name))
    m = record.metrics
    for name, value in (("gpu_name", m.memory.gpu_name), ("outputs_sha256", m.task.outputs_sha256)):
        out[name] = value if isinstance(value, str) else ""
    out["latency_e2e_p50_ms"] = _plain(number(m.latency_e2e and m.latency_e2e.p50))
    for name, size in (("size", m.size.bytes), ("size_gzip", m.size.gzip_bytes)):
        out[f"{name}_mib"] = "" if number(size) is None else round(size / MIB, 6)
    for stat in LATENCY_STATS:
        out[f"latency_{stat}_ms"] = _plain(number(m.latency and getattr(m.latency, stat)))
    out["latency_n"] = _plain(number(m.latency and m.latency.n))
    out["latency_attempts"] = _plain(number(m.passes.attempts))
    out["latency_stability"] = _plain(number(m.passes.stability))
    for prefix, series in (("latency", m.latency), ("latency_e2e", m.latency_e2e)):
        low, high = _interval(series)
        out[f"{prefix}_p50_ci_low_ms"], out[f"{prefix}_p50_ci_high_ms"] = _plain(low), _plain(high)
    phases = disturbed_phases(record)
    out["interference_flagged"] = "" if record.status != "ok" else str(bool(phases)).lower()
    out["interference_reason"] = " | ".join(f"{name}: {why}" for name, why in phases.items())
    cached = m.others.get("artifact_cached")
    out["artifact_cached"] = "" if not isinstance(cached, bool) else str(cached).lower()
    out["speedup_vs_baseline"] = _plain(row.speedup if row else None)
    out["size_ratio_vs_baseline"] = _plain(row.size_ratio if row else None)
    out["mse_delta_vs_baseline"] = _plain(row.mse_delta if row else None)
    out["accuracy_delta_vs_baseline"] = _plain(row.accuracy_delta if row else None)
    verdict = row.verdict if row else None
    out["verdict"] = verdict.status if verdict else ""
    named = (verdict.failed or verdict.uncertain) if verdict else ()
    out["verdict_missed"] = " | ".join(check.text for check in named)
    return out


def _interval(stats: LatencyStats | None) -> tuple[float | None, float | None]:
    """The stored 95 % interval [lo, hi] of a series' p50, or (None, None)."""
    interval = stats.p50_ci if stats is not None else None
    if isinstance(interval, tuple) and len(interval) == 2:
        return number(interval[0]), number(interval[1])
    return None, None


def _plain(value: float | None) -> float | int | str:
    """A number for the CSV (whole numbers without ".0"), or "" when missing."""
    if value is None:
        return ""
    return int(value) if value.is_integer() else value
