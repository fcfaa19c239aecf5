"""The jobs a worker process runs: probe backends, prepare dataset and model, convert, measure."""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix import data, hardware
from bench_matrix.backends.base import Backend, ConvertRequest, Session
from bench_matrix.backends.registry import BackendLoadError, load_backend
from bench_matrix.errors import UserError
from bench_matrix.matrix.schema import STRATEGY_KINDS
from bench_matrix.matrix.spec import ModelSpec, StrategySpec
from bench_matrix.measure import env as environment
from bench_matrix.measure.gpu import GpuMemory
from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import accuracy, latency_summary
from bench_matrix.measure.timing import LoopSettings, steady_time_calls, throughput
from bench_matrix.sources import SourceModel
from bench_matrix.worker import phase
from bench_matrix.workspace import Workspace, digest, file_sha256

NONE = StrategySpec(name="none", kind="none")
LATENCY_INPUTS = 16
GPU_TARGETS = ("cuda", "tensorrt")  # timed compute-only and end to end; GPU name and memory recorded
_DEFAULT_FORMAT = {"pytorch": "state_dict", "tensorflow": "keras"}  # what built-in models arrive as


def probe(job: dict[str, Any]) -> dict[str, Any]:
    """Describe each backend and judge each (backend, framework, kind, precision, target) combination."""
    backends: dict[str, Backend | None] = {}
    described: dict[str, Any] = {}
    for name in job["backends"]:
        try:
            b = load_backend(name)
            backends[name] = b
            described[name] = {"error": None, "description": b.description, "versions": b.versions(),
                               "baseline_for": list(b.baseline_for),
                               "supports": [{k: list(getattr(s, k)) for k in ("frameworks", "strategies",
                                             "precisions", "targets")} for s in b.supports]}
        except BackendLoadError as exc:
            backends[name], described[name] = None, {"error": str(exc)}
    keys = job["keys"]
    if keys == "declared":  # every combination the loaded backends declare, for a default source
        keys = [(n, f, st, p, t, _DEFAULT_FORMAT.get(f, f), "{}") for n, b in backends.items() if b
                for s in b.supports for f in s.frameworks for st in s.strategies for p in s.precisions
                for t in s.targets]
    verdicts = {}
    for key in keys:
        name, framework, kind, precision, target, source_format, options = key
        b = backends[name]
        if b is None:
            verdicts[json.dumps(key)] = {"invalid": None, "skip": described[name]["error"]}
            continue
        invalid = (b.invalid_reason(framework, kind, precision, target)
                   or b.option_reason(StrategySpec(name=kind, kind=kind, options=json.loads(options)), source_format))
        try:
            reasons = [] if invalid else [b.probe(target, precision), b.probe_source(framework, source_format)]
            skip = "; ".join(r for r in reasons if r) or None
        except Exception as exc:  # a probe that crashes is a reason, not a crash of the run
            skip = f"probing {name} for {target}/{precision} failed: {type(exc).__name__}: {exc}"
        verdicts[json.dumps(key)] = {"invalid": invalid, "skip": skip}
    return {"backends": described, "verdicts": verdicts, "trainers": judge_training(job.get("training", []))}


def judge_training(keys: list[list[str]]) -> dict[str, dict[str, Any]]:
    """For each (framework, source format, steps) the first installed trainer that can apply it, or why none."""
    from bench_matrix.strategies.registry import TrainerLoadError, load_trainer, trainer_names

    trainers, errors = [], []
    for name in trainer_names():
        try:
            trainers.append(load_trainer(name))
        except TrainerLoadError as exc:
            errors.append(str(exc))
    verdicts = {}
    for framework, source_format, steps_json in keys:
        steps = tuple(StrategySpec.from_dict(s) for s in json.loads(steps_json))
        kinds = ", ".join(s.kind or "" for s in steps)
        judged = [(t, t.steps_reason(steps, source_format)) for t in trainers if t.framework == framework]
        reasons = [f"{t.name}: {r}" for t, r in judged if r]
        able = [t for t, r in judged if not r]
        if not able:
            why = "; ".join(reasons + errors) or f"no installed trainer fine-tunes {framework} models"
            verdicts[json.dumps([framework, source_format, steps_json])] = {"invalid": f"{kinds}: {why}"}
            continue
        try:
            skip = able[0].probe()
        except Exception as exc:  # a probe that crashes is a reason, not a crash of the run
            skip = f"probing trainer {able[0].name} failed: {type(exc).__name__}: {exc}"
        verdicts[json.dumps([framework, source_format, steps_json])] = {"skip": skip, "by": able[0].name}
    return verdicts


def prepare_dataset(job: dict[str, Any]) -> dict[str, Any]:
    """Read, check, preprocess and split the user's dataset (cached); a mistake in it is a UserError."""
    phase("dataset")
    try:
        directory, info = data.prepare(job["dataset"], Workspace(Path(job["workspace"])))
    except MemoryError:
        raise UserError(f"{data.source(job['dataset'])}: the dataset does not fit in this machine's memory; "
                        f"use fewer samples or smaller images (dataset.preprocess.crop, resize)") from None
    return {"dir": str(directory), "info": info}


def prepare_model(job: dict[str, Any]) -> dict[str, Any]:
    """Materialise the source model (training built-ins), check it, and compute the fp32 reference outputs."""
    spec: ModelSpec = job["model"]
    ws = Workspace(Path(job["workspace"]))
    ddir, dinfo, settings = Path(job["dataset_dir"]), job["dataset_info"], job["settings"]
    key = digest({"model": spec, "dataset": dinfo["fingerprint"], "seed": settings.seed,
                  "eval": settings.eval_samples, "files": _spec_files_sha(spec), "format": 1,
                  "baseline": [job["baseline_backend"], environment.library_versions()]})
    out = ws.models(key)
    if (out / "prepared.json").is_file():
        return json.loads((out / "prepared.json").read_text())
    phase("prepare")
    h, w, c = dinfo["sample_shape"]
    shape = (c, h, w) if spec.layout == "nchw" else (h, w, c)
    source, training = _source(spec, ws, ddir, dinfo, job["preprocess"], settings, shape)
    baseline = load_backend(job["baseline_backend"])
    artifact, manifest, _ = ensure_artifact(ws, baseline, source, NONE, "fp32", "cpu", ddir, dinfo,
                                            job["preprocess"], spec.layout, settings)
    session = baseline.load(artifact / "model", manifest["meta"], "cpu", "fp32", settings.threads)
    x, y = data.load_split(ddir, "test", job["preprocess"], spec.layout, settings.eval_samples)
    pred = predict_all(session, x, settings.batch_size)
    if pred.reshape(len(y), -1).shape != y.shape:
        raise UserError(f"model {spec.name} outputs {pred.shape[1:]} per sample but the dataset has "
                        f"{y.shape[1]} label column(s) ({', '.join(dinfo['label_columns'])})")
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "reference.npy", pred)
    info = {"framework": spec.framework, "source": _describe(spec), "params": manifest["params"],
            "sha256": source.sha256, "baseline_key": "/".join((spec.name, baseline.name, "none", "fp32", "cpu")),
            "test_mse": accuracy(pred, y, None)["mse"], "mean_predictor_mse": dinfo["mean_predictor_mse"],
            "test_samples": int(len(y)), "training": training}
    result = {"source": source.to_dict(), "info": info, "reference": str(out / "reference.npy")}
    (out / "prepared.json").write_text(json.dumps(result, indent=1))
    return result


def finetune(job: dict[str, Any]) -> dict[str, Any]:
    """Fine-tune the pristine source with the strategy's training steps, once per content hash; the new source."""
    from bench_matrix.matrix.expand import training_steps
    from bench_matrix.strategies.base import FineTuneRequest
    from bench_matrix.strategies.registry import load_trainer

    ws, settings, dinfo = Workspace(Path(job["workspace"])), job["settings"], job["dataset_info"]
    source, trainer = SourceModel.from_dict(job["source"]), load_trainer(job["trainer"])
    steps = training_steps(job["strategy"])
    key = digest({"source": source.sha256, "trainer": trainer.name, "revision": trainer.revision,
                  "versions": trainer.versions(), "steps": [s.to_dict() for s in steps],
                  "dataset": dinfo["fingerprint"], "layout": job["layout"], "seed": settings.seed})
    final = ws.root / "cache" / "finetuned" / key
    if not (final / "finetuned.json").is_file():
        phase("finetune")
        tmp = final.with_name(f"{final.name}.tmp{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        (tmp / "model").mkdir(parents=True)

        def train(fraction: float) -> tuple[np.ndarray, np.ndarray]:
            x, y = data.load_split(Path(job["dataset_dir"]), "train", job["preprocess"], job["layout"])
            order = np.random.default_rng(settings.seed).permutation(len(x))[:max(1, round(len(x) * fraction))]
            return x[np.sort(order)], y[np.sort(order)]

        request = FineTuneRequest(source=source, steps=steps, out_dir=tmp / "model", train=train,
                                  threads=len(os.sched_getaffinity(0)), seed=settings.seed)
        begin = time.perf_counter()
        result = trainer.finetune(request)
        facts = {**result.facts, "finetune_s": time.perf_counter() - begin, "trainer": trainer.name,
                 "trainer_versions": trainer.versions()}
        (tmp / "finetuned.json").write_text(json.dumps({"file": result.file, "format": result.format,
                                                        "facts": facts}, default=str))
        try:
            tmp.rename(final)
        except OSError:  # another process finished the same fine-tuning first: keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
    done = json.loads((final / "finetuned.json").read_text())
    path = final / "model" / done["file"]
    tuned = SourceModel(name=source.name, framework=source.framework, format=done["format"], path=path,
                        sha256=file_sha256(path), input_shape=source.input_shape, factory=source.factory,
                        python_path=source.python_path, origin=source.origin or str(source.path))
    return {"source": tuned.to_dict(), "facts": done["facts"]}


def convert(job: dict[str, Any]) -> dict[str, Any]:
    phase("convert")
    source = SourceModel.from_dict(job["source"])
    artifact, manifest, cached = ensure_artifact(
        Workspace(Path(job["workspace"])), load_backend(job["cell"].backend), source, job["strategy"],
        job["cell"].precision, job["cell"].target, Path(job["dataset_dir"]), job["dataset_info"],
        job["preprocess"], job["layout"], job["settings"])
    return {"artifact_dir": str(artifact), "manifest": manifest, "cached": cached}


def measure(job: dict[str, Any]) -> dict[str, Any]:
    """Load, time at batch 1, time throughput, record peak memory, then evaluate accuracy."""
    cell, settings, layout, pre = job["cell"], job["settings"], job["layout"], job["preprocess"]
    ddir, artifact, manifest = Path(job["dataset_dir"]), Path(job["artifact_dir"]), job["manifest"]
    backend = load_backend(cell.backend)
    x_few, _ = data.load_split(ddir, "test", pre, layout, max(LATENCY_INPUTS, settings.batch_size))
    on_gpu = cell.target in GPU_TARGETS
    gpu_memory = GpuMemory() if on_gpu else None  # before the load: the fallback reading subtracts this
    phase("load")
    begin = time.perf_counter()
    session = backend.load(artifact / "model", manifest["meta"], cell.target, cell.precision, settings.threads)
    load_s = time.perf_counter() - begin
    singles = [session.prepare(x_few[i:i + 1]) for i in range(min(LATENCY_INPUTS, len(x_few)))]
    batch = session.prepare(np.resize(x_few, (settings.batch_size, *x_few.shape[1:])))
    loop = LoopSettings(settings.warmup_iterations, settings.warmup_s, settings.min_iterations,
                        settings.min_time_s, settings.max_time_s)
    phase("measure")
    durations, stability = steady_time_calls(session.execute, singles, loop)
    gpu: dict[str, Any] = {}
    if on_gpu:  # end to end: from host arrays, both copies and fetch inside the clock
        hosts = [x_few[i:i + 1] for i in range(len(singles))]
        gpu["latency_ms_e2e"] = latency_summary(steady_time_calls(session.predict, hosts, loop)[0])
    rate = throughput(session.execute, batch, settings.batch_size, settings.throughput_time_s)
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    phase("evaluate")
    x, y = data.load_split(ddir, "test", pre, layout, settings.eval_samples)
    pred = predict_all(session, x, settings.batch_size)
    if gpu_memory is not None:
        gpu.update(gpu_name=hardware.gpus()[0].name if hardware.gpus() else None, **gpu_memory.peak())
    reference = np.load(job["reference"]) if job.get("reference") else None
    metrics = {**artifact_size(artifact / "model", artifact / "size.json"), "params": manifest["params"],
               **accuracy(pred, y, reference), "outputs_sha256": outputs_digest(pred),
               "latency_ms": latency_summary(durations), **gpu, **stability, **rate,
               "batch_size": settings.batch_size, "peak_rss_mb": round(peak_rss_mb, 1),
               "convert_s": manifest["convert_s"], "load_s": load_s, "threads": settings.threads,
               "artifact_cached": job["cached"], "session": session.info(), "test_samples": int(len(y)),
               **_finetune_metrics(job.get("finetune"), manifest["convert_s"])}
    return {"metrics": metrics, "env": {**environment.capture(), "backend_versions": backend.versions(),
                                        "runtime": session.info()}}


def _finetune_metrics(facts: dict[str, Any] | None, convert_s: float) -> dict[str, Any]:
    """For a fine-tuned model: convert_s including the fine-tuning, finetune_s, sparsity, clusters (when it was
    clustered: elsewhere the most distinct values per kernel is just its size), the facts."""
    if not facts:
        return {}
    clusters = facts.get("clusters") if "target_clusters" in facts else None
    return {"convert_s": convert_s + facts["finetune_s"], "finetune_s": facts["finetune_s"],
            "sparsity": facts.get("sparsity"), "clusters": clusters, "finetune": facts}


def outputs_digest(pred: np.ndarray) -> str:
    """SHA-256 of the predictions as contiguous float32: equal only for bit-identical outputs."""
    return hashlib.sha256(np.ascontiguousarray(pred, dtype=np.float32).tobytes()).hexdigest()


def predict_all(session: Session, x: np.ndarray, batch_size: int) -> np.ndarray:
    return np.concatenate([session.predict(x[i:i + batch_size]) for i in range(0, len(x), batch_size)])


def ensure_artifact(ws: Workspace, backend: Backend, source: SourceModel, strategy: StrategySpec,
                    precision: str, target: str, ddir: Path, dinfo: dict, preprocess: Any, layout: str,
                    settings: Any) -> tuple[Path, dict[str, Any], bool]:
    """Convert once per content hash (source, strategy, options, libraries, calibration data); reuse after."""
    calibrated = any("calibration_samples" in STRATEGY_KINDS[k]["options"] for k in strategy.kinds())
    # A TensorRT engine covers batches up to max_batch and runs only on the GPU model it was built for.
    engine = ({"max_batch": settings.batch_size, "gpu": [(g.name, g.capability) for g in hardware.gpus()[:1]]}
              if target == "tensorrt" else {})
    key = digest({"source": source.sha256, "backend": backend.name, "versions": backend.versions(),
                  "strategy": strategy.to_dict(), "precision": precision, "target": target,
                  "calibration": [dinfo["fingerprint"], layout] if calibrated else None, "seed": settings.seed,
                  **engine})
    final = ws.artifact(backend.name, key)
    if (final / "manifest.json").is_file():
        return final, json.loads((final / "manifest.json").read_text()), True
    tmp = final.with_name(f"{final.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "model").mkdir(parents=True)

    def calibration(n: int) -> np.ndarray:
        return data.load_split(ddir, "calibration", preprocess, layout, n)[0]

    shared = ws.intermediates(backend.name, digest({"source": source.sha256, "versions": backend.versions(),
                                                    "seed": settings.seed}))
    shared.mkdir(parents=True, exist_ok=True)
    request = ConvertRequest(source=source, strategy=strategy, precision=precision, target=target,
                             out_dir=tmp / "model", calibration=calibration, threads=settings.threads,
                             seed=settings.seed, shared_dir=shared, max_batch=settings.batch_size)
    begin = time.perf_counter()
    try:
        meta = backend.convert(request)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    convert_s = time.perf_counter() - begin
    manifest = {"meta": meta, "convert_s": convert_s, "params": _params(ws, source),
                "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "versions": backend.versions(), "source_sha256": source.sha256, "strategy": strategy.to_dict(),
                "precision": precision, "target": target}
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, default=str))
    try:
        tmp.rename(final)
    except OSError:  # another process finished the same artifact first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return final, json.loads((final / "manifest.json").read_text()), False


def _params(ws: Workspace, source: SourceModel) -> int:
    """The source's parameter count, counted once per content hash (counting loads the model)."""
    kept = ws.root / "cache" / "params" / f"{source.sha256}.json"
    if kept.is_file():
        return int(json.loads(kept.read_text()))
    params = _count_params(source)
    kept.parent.mkdir(parents=True, exist_ok=True)
    partial = kept.with_name(f"{kept.name}.tmp{os.getpid()}")
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


def _source(spec: ModelSpec, ws: Workspace, ddir: Path, dinfo: dict, preprocess: Any, settings: Any,
            shape: tuple[int, ...]) -> tuple[SourceModel, dict[str, Any] | None]:
    if spec.builtin:
        return _trained_builtin(spec, ws, ddir, dinfo, preprocess, settings, shape)
    if spec.file:
        return SourceModel(spec.name, spec.framework, spec.source_format, spec.file, file_sha256(spec.file), shape), None
    assert spec.weights is not None and spec.factory is not None
    return (SourceModel(spec.name, "pytorch", "state_dict", spec.weights, file_sha256(spec.weights), shape,
                        factory=spec.factory, python_path=tuple(str(p) for p in spec.python_path)), None)


def _trained_builtin(spec: ModelSpec, ws: Workspace, ddir: Path, dinfo: dict, preprocess: Any, settings: Any,
                     shape: tuple[int, ...]) -> tuple[SourceModel, dict[str, Any]]:
    """The built-in model of spec.framework, trained on the training split once and cached by content."""
    from bench_matrix.workload.pilotnet_torch import FACTORIES

    key = digest({"builtin": spec.builtin, "framework": spec.framework, "training": spec.training,
                  "dataset": dinfo["fingerprint"], "seed": settings.seed, "layout": spec.layout})
    keras = spec.framework == "tensorflow"
    model_file = ws.models(key) / ("model.keras" if keras else "model.pt")
    facts_file = model_file.with_name("training.json")
    if not facts_file.is_file():
        phase("train")
        from bench_matrix.workload.train import train_keras, train_torch

        x, y = data.load_split(ddir, "train", preprocess, spec.layout)
        threads = len(os.sched_getaffinity(0))
        facts = (train_keras(spec.builtin, x, y, spec.training, settings.seed, model_file, threads) if keras else
                 train_torch(FACTORIES[spec.builtin], x, y, spec.training, settings.seed, model_file, threads))
        facts_file.write_text(json.dumps(facts))
    facts = json.loads(facts_file.read_text())
    if keras:
        return SourceModel(spec.name, "tensorflow", "keras", model_file, file_sha256(model_file), shape), facts
    return (SourceModel(spec.name, "pytorch", "state_dict", model_file, file_sha256(model_file), shape,
                        factory=FACTORIES[spec.builtin]), facts)


def _spec_files_sha(spec: ModelSpec) -> list[str]:
    return [file_sha256(p) for p in (spec.file, spec.weights) if p is not None]


def _describe(spec: ModelSpec) -> str:
    if spec.builtin:
        return f"builtin {spec.builtin} (trained on the dataset's training split)"
    return str(spec.file) if spec.file else f"{spec.factory} + {spec.weights}"
