"""Preparation jobs: the dataset's splits, each model's source and fp32 reference outputs, fine-tuned sources."""

from __future__ import annotations

import json
import os
import shutil
import time
from typing import Any

import numpy as np

from bench_matrix import data
from bench_matrix.backend import Backend
from bench_matrix.cell import NO_STEP
from bench_matrix.errors import UserError
from bench_matrix.images import layout_note
from bench_matrix.phases import phase
from bench_matrix.jobs import DatasetJob, FinetuneJob, ModelJob, ReferenceJob
from bench_matrix.jobs.artifact import ensure_artifact, predict_all
from bench_matrix.jobs.keys import builtin_key, finetune_key, model_key
from bench_matrix.jobs.results import Converted, Finetuned, PreparedData, PreparedModel, Reference
from bench_matrix.matrix.spec import ModelSpec, Settings
from bench_matrix.measure import env as environment
from bench_matrix.measure.metrics import evaluate, non_finite_reason
from bench_matrix.registry import load_backend
from bench_matrix.sources import SourceModel
from bench_matrix.sources.code import model_code
from bench_matrix.tensors import TensorSpec, binding_problem, bind, fed, open_axes, take
from bench_matrix.workspace import Workspace, digest, file_sha256


def prepare_dataset(job: DatasetJob) -> PreparedData:
    """Read, check, preprocess and split the user's dataset (cached); a mistake in it is a UserError."""
    phase("dataset")
    try:
        directory, info = data.prepare(job.dataset, job.workspace, job.inputs or None, job.as_is)
    except MemoryError:
        raise UserError(f"{data.source(job.dataset)}: the dataset does not fit in this machine's memory; "
                        f"use fewer samples or smaller images (dataset.preprocess.crop, resize)") from None
    return PreparedData(directory, info, job.dataset.preprocess)


def prepare_model(job: ModelJob) -> PreparedModel:
    """Materialise the source model (training built-ins), check it, and compute the fp32 reference outputs."""
    spec, ws, settings, prepared = job.model, job.workspace, job.settings, job.data
    inputs = job.inputs or data.data_inputs(prepared.info, spec.layout)
    key = model_key(spec, inputs, model_code(spec), job.task, prepared.fingerprint, settings,
                    [job.baseline.backend, environment.library_versions()])
    out = ws.models(key)
    if (out / "prepared.json").is_file():  # paths are derived afresh: the workspace may be named otherwise now
        source, _ = _source(spec, ws, prepared, settings.seed, inputs)
        info = json.loads((out / "prepared.json").read_text())["info"]
        return PreparedModel(source, {**info, **_timed(spec, prepared, inputs)}, out / "reference.npz")
    phase("prepare")
    _check_binding(spec, prepared, inputs)
    source, training = _source(spec, ws, prepared, settings.seed, inputs)
    baseline = load_backend(job.baseline.backend)
    converted = ensure_artifact(ws, baseline, source, NO_STEP, "fp32", "cpu", prepared, spec.layout, settings,
                                {})
    outputs, y = _baseline_outputs(baseline, converted, source, inputs, prepared, spec.layout, settings)
    if reason := non_finite_reason(outputs):
        raise UserError(f"model {spec.name}: its fp32 outputs on the test split are not finite ({reason})")
    _check_outputs(spec, job.task, outputs, y, prepared.info)
    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / "reference.npz", *outputs)
    info = {"framework": spec.framework, "source": job.described, "params": converted.manifest["params"],
            "sha256": source.sha256, "baseline_key": job.baseline.key, "task": job.task,
            "inputs": [i.to_dict() for i in inputs], "outputs": [list(o.shape[1:]) for o in outputs],
            "test_metrics": evaluate(job.task, outputs, y, None), "test_samples": int(len(outputs[0])),
            "training": training, **_chance(prepared.info), **_timed(spec, prepared, inputs)}
    if job.task == "regression":
        info["test_mse"] = info["test_metrics"]["mse"]
    (out / "prepared.json").write_text(json.dumps({"info": info}, indent=1))
    return PreparedModel(source, info, out / "reference.npz")


def reference_outputs(job: ReferenceJob) -> Reference:
    """The baseline artifact's fp32 outputs on the test split, kept by the artifact's folder and the data."""
    phase("reference")
    settings = job.settings
    out = job.workspace.references(digest([str(job.converted.directory), job.data.fingerprint, job.layout,
                                           settings.eval_samples, settings.batch_size]))
    if not (out / "reference.npz").is_file():
        outputs, _ = _baseline_outputs(load_backend(job.baseline.backend), job.converted, job.source,
                                       job.source.inputs, job.data, job.layout, settings)
        partial = job.workspace.partial(out / "reference.npz")
        np.savez(partial, *outputs)
        partial.replace(out / "reference.npz")
    return Reference(out / "reference.npz")


def _baseline_outputs(baseline: Backend, converted: Converted, source: SourceModel,
                      inputs: tuple[TensorSpec, ...], prepared: PreparedData, layout: str, settings: Settings
                      ) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The baseline artifact's outputs on the test split (settings.eval_samples of it), and its labels."""
    try:
        session = baseline.load(converted.model, converted.manifest["meta"], "cpu", "fp32", settings.threads)
    except Exception as exc:  # e.g. an operator of a custom domain the runtime does not have
        said = str(exc).replace(str(converted.model), "its converted copy")
        raise RuntimeError(f"{source.origin or source.path}: {baseline.name} cannot load it: {said}") from exc
    x, y = data.load_split(prepared.directory, "test", prepared.preprocess, layout, settings.eval_samples)
    return predict_all(session, bind(x, inputs), settings.batch_size), y


def _timed(spec: ModelSpec, prepared: PreparedData, inputs: tuple[TensorSpec, ...]) -> dict[str, Any]:
    """The shapes the inputs are timed at (the data's, per sample) and the open axes of each that synthetic
    data gave the default length."""
    given = {i.name: i for i in data.data_inputs(prepared.info, spec.layout)}
    synthetic = prepared.info.get("kind") == "synthetic"
    timed = [{"name": i.name, "shape": list(i.shape), "dtype": i.dtype} for i in fed(given, inputs)]
    return {"timed_inputs": timed,
            "defaulted_axes": {i.name: list(open_axes(i)) for i in inputs if synthetic and open_axes(i)}}


def _chance(info: dict[str, Any]) -> dict[str, Any]:
    """What guessing scores on this data: the mean predictor's MSE, the majority class's top-1."""
    return {k: info[k] for k in ("mean_predictor_mse", "majority_top1", "classes", "label_columns") if k in info}


def _check_binding(spec: ModelSpec, prepared: PreparedData, inputs: tuple[TensorSpec, ...]) -> None:
    given = {i.name: i for i in data.data_inputs(prepared.info, spec.layout)}
    if problem := binding_problem(given, inputs):
        images = {i["name"]: tuple(i["shape"]) for i in prepared.info["inputs"] if i["image"]}
        raise UserError(f"model {spec.name}: {problem}{layout_note(images, spec.layout)}")


def _check_outputs(spec: ModelSpec, task: str, outputs: list[np.ndarray], y: np.ndarray | None,
                   info: dict[str, Any]) -> None:
    """The outputs fit the task: as many values as label columns (regression), logits over the classes."""
    shapes = ", ".join(str(tuple(o.shape[1:])) for o in outputs)
    if task == "regression":
        width = sum(int(np.prod(o.shape[1:])) for o in outputs)
        if y is not None and width != y.reshape(len(y), -1).shape[1]:
            raise UserError(f"model {spec.name} outputs {shapes} per sample ({width} values) but the dataset has "
                            f"{y.reshape(len(y), -1).shape[1]} label column(s) "
                            f"({', '.join(info.get('label_columns', []))}); for class labels set task: "
                            f"classification")
    elif task == "classification":
        classes = len(info.get("classes") or []) or (int(y.max()) + 1 if y is not None and len(y) else 0)
        if outputs[0].ndim != 2 or outputs[0].shape[1] < max(classes, 2):
            raise UserError(f"model {spec.name} outputs {shapes} per sample, but classification needs its first "
                            f"output to be logits over the {classes} classes of the dataset, shape ({classes},)")


def finetune(job: FinetuneJob) -> Finetuned:
    """Fine-tune the pristine source with the training steps, once per content hash; the new source."""
    from bench_matrix.strategies.base import FineTuneRequest
    from bench_matrix.strategies.registry import load_trainer

    ws, source, trainer = job.workspace, job.source, load_trainer(job.trainer)
    key = finetune_key(trainer, source, job.steps, job.task, [job.data.fingerprint, job.layout],
                       job.seed)
    final = ws.finetuned(key)
    if not (final / "finetuned.json").is_file():
        phase("finetune")
        tmp = ws.partial(final)
        (tmp / "model").mkdir(parents=True)

        def train(fraction: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
            x, y = data.load_split(job.data.directory, "train", job.data.preprocess, job.layout)
            n = len(y)
            order = np.sort(np.random.default_rng(job.seed).permutation(n)[:max(1, round(n * fraction))])
            return take(bind(x, source.inputs), order), y[order]

        request = FineTuneRequest(source=source, steps=job.steps, out_dir=tmp / "model", train=train,
                                  threads=len(os.sched_getaffinity(0)), seed=job.seed, task=job.task)
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
                        sha256=file_sha256(path), inputs=source.inputs, factory=source.factory,
                        python_path=source.python_path, origin=source.origin or str(source.path),
                        code_sha256=source.code_sha256)
    return Finetuned(tuned, done["facts"])


def _source(spec: ModelSpec, ws: Workspace, prepared: PreparedData, seed: int,
            inputs: tuple[TensorSpec, ...]) -> tuple[SourceModel, dict[str, Any] | None]:
    if spec.builtin:
        return _trained_builtin(spec, ws, prepared, seed, inputs)
    if spec.file:
        return SourceModel(spec.name, spec.framework, spec.source_format, spec.file, file_sha256(spec.file),
                           inputs), None
    assert spec.weights is not None and spec.factory is not None
    return (SourceModel(spec.name, "pytorch", "state_dict", spec.weights, file_sha256(spec.weights), inputs,
                        factory=spec.factory, python_path=tuple(str(p) for p in spec.python_path),
                        code_sha256=model_code(spec)), None)


def _trained_builtin(spec: ModelSpec, ws: Workspace, prepared: PreparedData, seed: int,
                     inputs: tuple[TensorSpec, ...]) -> tuple[SourceModel, dict[str, Any]]:
    """The built-in model of spec.framework, trained on the training split once and cached by content."""
    from bench_matrix.workload.pilotnet_torch import FACTORIES

    key = builtin_key(spec, model_code(spec), prepared.fingerprint, seed, environment.library_versions())
    keras = spec.framework == "tensorflow"
    model_file = ws.models(key) / ("model.keras" if keras else "model.pt")
    facts_file = model_file.with_name("training.json")
    if not facts_file.is_file():
        phase("train")
        from bench_matrix.workload.train import train_keras, train_torch

        x, y = data.load_split(prepared.directory, "train", prepared.preprocess, spec.layout)
        x = bind(x, inputs)
        threads = len(os.sched_getaffinity(0))
        partial = ws.partial(model_file)
        facts = (train_keras(spec.builtin, x, y, spec.training, seed, partial, threads) if keras else
                 train_torch(FACTORIES[spec.builtin], x, y, spec.training, seed, partial, threads))
        partial.replace(model_file)
        facts_file.write_text(json.dumps(facts))
    facts = json.loads(facts_file.read_text())
    if keras:
        return SourceModel(spec.name, "tensorflow", "keras", model_file, file_sha256(model_file), inputs), facts
    return (SourceModel(spec.name, "pytorch", "state_dict", model_file, file_sha256(model_file), inputs,
                        factory=FACTORIES[spec.builtin], code_sha256=model_code(spec)), facts)
