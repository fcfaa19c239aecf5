"""The convert job, and artifacts: convert a source once per content hash and reuse it after; run a session
over many samples."""

from __future__ import annotations

import json
import shutil
import time
from datetime import datetime, timezone
from typing import Any

import numpy as np

from bench_matrix import data
from bench_matrix.backend import Backend, ConvertRequest, Session
from bench_matrix.phases import phase
from bench_matrix.jobs import ConvertJob
from bench_matrix.jobs.keys import artifact_key, calibrates, intermediates_key, params_key
from bench_matrix.jobs.results import Converted, PreparedData
from bench_matrix.matrix.spec import Settings
from bench_matrix.strategy import StrategySpec
from bench_matrix.registry import load_backend
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs, bind, count, take
from bench_matrix.workspace import Workspace


def convert(job: ConvertJob) -> Converted:
    """Convert the cell's source into its artifact, or find it converted already."""
    phase("convert")
    cell = job.cell
    return ensure_artifact(job.workspace, load_backend(cell.backend), job.source, job.step, cell.precision,
                           cell.target, job.data, job.layout, job.settings, job.options)


def ensure_artifact(ws: Workspace, backend: Backend, source: SourceModel, step: StrategySpec, precision: str,
                    target: str, prepared: PreparedData, layout: str, settings: Settings,
                    options: dict[str, Any]) -> Converted:
    """Convert once per content (keys.artifact_key); reuse after."""
    key = artifact_key(backend, source, step, precision, target, [prepared.fingerprint, layout],
                       settings, options)
    final = ws.artifact(backend.name, key)
    if (final / "manifest.json").is_file():
        return Converted(final, json.loads((final / "manifest.json").read_text()), True)
    tmp, scratch = ws.partial(final), ws.partial(final.with_name("scratch"))
    (tmp / "model").mkdir(parents=True)
    scratch.mkdir()

    reads: list[tuple[int, int]] = []  # (asked, given) of each read of the calibration split

    def calibration(n: int) -> Inputs:
        x, _ = data.load_split(prepared.directory, "calibration", prepared.preprocess, layout, n)
        reads.append((n, count(x)))
        return bind(x, source.inputs)

    shared = ws.intermediates(backend.name, intermediates_key(backend, source, settings.seed))
    shared.mkdir(parents=True, exist_ok=True)
    request = ConvertRequest(source=source, step=step, precision=precision, target=target, out_dir=tmp / "model",
                             calibration=calibration, threads=settings.threads, seed=settings.seed,
                             shared_dir=shared, max_batch=settings.batch_size, options=options,
                             scratch_dir=scratch)
    begin = time.perf_counter()
    try:
        meta = backend.convert(request)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    manifest = {"meta": meta, "convert_s": time.perf_counter() - begin, "params": _params(ws, source),
                "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "versions": backend.versions(), "source_sha256": source.sha256, "step": step.to_dict(),
                "precision": precision, "target": target, "options": options,
                "calibration": _calibration(reads) if calibrates(step) else None}
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, default=str))
    try:
        tmp.rename(final)
    except OSError:  # another process finished the same artifact first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return Converted(final, json.loads((final / "manifest.json").read_text()), False)


def _calibration(reads: list[tuple[int, int]]) -> dict[str, int] | None:
    """How many calibration samples the conversion asked for at most, and how many the split gave it."""
    if not reads:
        return None
    asked, used = max(reads)
    return {"asked": asked, "used": used}


def predict_all(session: Session, inputs: Inputs, batch_size: int) -> list[np.ndarray]:
    """Every output of the model over all samples, batch by batch, concatenated per output."""
    n = count(inputs)
    parts = [session.predict(take(inputs, slice(i, i + batch_size))) for i in range(0, n, batch_size)]
    return [np.concatenate([p[k] for p in parts]) for k in range(len(parts[0]))]


def _params(ws: Workspace, source: SourceModel) -> int:
    """The source's parameter count, counted once per source (counting loads the model)."""
    kept = ws.params(params_key(source))
    if kept.is_file():
        return int(json.loads(kept.read_text()))
    params = _count_params(source)
    partial = ws.partial(kept)
    partial.write_text(json.dumps(params))
    partial.replace(kept)  # a reader never sees a half-written count
    return params


def _count_params(source: SourceModel) -> int:
    if source.framework == "onnx":
        from bench_matrix.sources.onnx_file import load_onnx

        return int(sum(np.prod(t.dims) for t in load_onnx(source.path, source.label).graph.initializer))
    if source.framework == "tensorflow":
        from bench_matrix.sources.tensorflow import count_params as count_keras_params

        return count_keras_params(source.load())
    from bench_matrix.sources.pytorch import count_params

    return count_params(source.load())
