"""TensorFlow Model Optimization trainer: pruning, clustering, QAT and their collaborative combinations
(cluster-, prune- and prune-cluster-preserving QAT) on Keras 2 (tf_keras) models.

Every training kind is a pipeline of phases applied in this fixed order: prune -> cluster -> qat.
  prune   = [prune]                 cluster = [cluster]              qat   = [qat]
  pqat    = [prune, qat]            cqat    = [cluster, qat]         pcqat = [prune, cluster, qat]
A combination of steps (e.g. steps [prune, qat]) builds the same pipeline from its steps, each phase taking
the options of the step it came from; later phases preserve what earlier ones did (sparsity-preserving
clustering, prune/cluster-preserving quantisation schemes).

Only Conv*/Dense kernels are pruned and clustered (biases, BatchNormalization and other layers stay dense),
and only layers tfmot's default 8-bit registry supports are annotated for QAT: a layer it does not know
(e.g. a BatchNormalization that does not follow a convolution, as in PilotNet's input normalisation) stays
float in the QAT model, and the facts name it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.plugin import QAT_KINDS, FineTuned, FineTuneRequest, StrategySpec, Trainer, \
    installed_versions, keras, tensorflow, weight_stats
from bench_matrix.sources.keras_qat import QAT_FORMAT, qat_custom_objects, tfmot_module
from bench_matrix.strategies.keras_fit import LOSSES, TrainingData, fit, training_data
from bench_matrix.strategies.tfmot_models import QAT_FILE, is_weighted, stored_kernels
from bench_matrix.strategies.tfmot_ranges import init_activation_ranges, observed_ranges

# Defaults of every option, per kind; a strategy's options override each one. Budgets follow the study
# (pruning 0.5 -> 0.8 polynomial over 2 epochs; CQAT 8 clusters kmeans++, 3 clustering + 1 QAT epochs;
# PQAT constant 0.5, 3 prune + 1 QAT epochs; PCQAT 3 + 3 + 1), on a quarter of the training split with a
# fine-tuning learning rate, so that each strategy costs minutes on 2 CPU cores.
# Kernels under min_weights weights stay dense when pruning: they save almost no storage and are the most
# sensitive (halving PilotNet's 10x2 or 50x10 output kernels alone takes its test MSE to the mean predictor's).
COMMON_DEFAULTS: dict[str, Any] = {"fraction": 0.25, "lr": 1e-4, "batch_size": 32, "min_weights": 10_000}
DEFAULTS: dict[str, dict[str, Any]] = {
    "prune": {"prune_epochs": 2, "initial_sparsity": 0.5, "final_sparsity": 0.8, "schedule": "polynomial"},
    "cluster": {"cluster_epochs": 3, "clusters": 8, "init": "kmeans++"},
    "qat": {"qat_epochs": 2},
    "cqat": {"cluster_epochs": 3, "qat_epochs": 1, "clusters": 8, "init": "kmeans++"},
    "pqat": {"prune_epochs": 3, "qat_epochs": 1, "initial_sparsity": 0.5, "final_sparsity": 0.5,
             "schedule": "constant"},
    "pcqat": {"prune_epochs": 3, "cluster_epochs": 3, "qat_epochs": 1, "initial_sparsity": 0.5,
              "final_sparsity": 0.5, "schedule": "constant", "clusters": 8, "init": "kmeans++"},
}
PHASES = {"prune": ("prune",), "cluster": ("cluster",), "qat": ("qat",), "pqat": ("prune", "qat"),
          "cqat": ("cluster", "qat"), "pcqat": ("prune", "cluster", "qat")}
ORDER = ("prune", "cluster", "qat")
RAMP_SHARE = 2 / 3  # the share of a polynomial prune phase spent raising sparsity
INITS = {"kmeans++": "KMEANS_PLUS_PLUS", "linear": "LINEAR", "density": "DENSITY_BASED", "random": "RANDOM"}
KERAS_FORMATS = ("keras", "h5", "saved_model")
def _phase_epochs(phase: str, kind: str, options: dict[str, Any]) -> float:
    """A phase's epochs: its own option (prune_epochs, ...), else `epochs`, else the kind's default."""
    own = f"{phase}_epochs"
    if own in options:
        return float(options[own])
    if "epochs" in options:
        return float(options["epochs"])
    return float(DEFAULTS[kind][own])


def _option(name: str, kind: str, options: dict[str, Any]) -> Any:
    if name in options:
        return options[name]
    if name in DEFAULTS[kind]:
        return DEFAULTS[kind][name]
    return COMMON_DEFAULTS.get(name)


def _plan(steps: tuple[StrategySpec, ...]) -> list[tuple[str, str, dict[str, Any]]]:
    """(phase, kind, options) in order, or ValueError with the reason."""
    plan = []
    for step in steps:
        if step.kind not in PHASES:
            raise ValueError(f"tfmot does not implement {step.kind!r} (it implements {', '.join(PHASES)})")
        plan += [(phase, step.kind, dict(step.options)) for phase in PHASES[step.kind]]
    phases = [p for p, _, _ in plan]
    if len(set(phases)) != len(phases) or phases != sorted(phases, key=ORDER.index):
        raise ValueError(f"tfmot applies prune, cluster and qat at most once each and in that order "
                         f"(prune -> cluster -> qat); these steps give {' -> '.join(phases)}")
    return plan


class TfmotTrainer(Trainer):
    name = "tfmot"
    description = ("TensorFlow Model Optimization: magnitude pruning, weight clustering, quantisation-aware "
                   "training and the collaborative CQAT/PQAT/PCQAT schemes on Keras 2 models")
    framework = "tensorflow"
    kinds = ("prune", "cluster", "qat", "cqat", "pqat", "pcqat")
    # 2: the polynomial ramp ends two thirds of the way; kernels below min_weights stay dense; BatchNorm frozen;
    #    QAT activation ranges start from the data. 3: a QAT model's sparsity and clusters are read from its
    #    fake-quantised kernels
    revision = 3

    def versions(self) -> dict[str, str]:
        return installed_versions("tensorflow", "tensorflow-cpu", "tf-keras", "tensorflow-model-optimization")

    def probe(self) -> str | None:
        try:
            tfmot_module()
        except Exception as exc:  # noqa: BLE001 - any import failure means it cannot run here
            return f"tensorflow-model-optimization is not importable ({exc}): pip install tensorflow-model-optimization"
        return None

    def output_format(self, steps: tuple[StrategySpec, ...], source_format: str) -> str:
        """A QAT model is saved as a SavedModel (keras_qat), any other as .keras."""
        return QAT_FORMAT if any(k in QAT_KINDS for s in steps for k in s.kinds()) else "keras"

    def steps_reason(self, steps: tuple[StrategySpec, ...], source_format: str,
                     task: str = "regression") -> str | None:
        reason = super().steps_reason(steps, source_format, task)
        if reason:
            return reason
        if source_format not in KERAS_FORMATS:
            return (f"tfmot fine-tunes Keras models ({', '.join(KERAS_FORMATS)}); this source is "
                    f"{source_format!r}")
        try:
            _plan(steps)
        except ValueError as exc:
            return str(exc)
        for step in steps:
            opts = step.options
            if opts.get("scope", "local") != "local":
                return (f"{step.name}: tfmot prunes each layer to its own target sparsity (scope: local); "
                        f"it has no global (whole-model) magnitude pruning")
            if "init" in opts and opts["init"] not in INITS:
                return f"{step.name}: tfmot has no centroid initialisation {opts['init']!r} ({', '.join(INITS)})"
            init_s = _option("initial_sparsity", step.kind, opts) if step.kind in ("prune", "pqat", "pcqat") else None
            for key in ("final_sparsity", "conv_sparsity", "linear_sparsity"):
                if init_s is not None and key in opts and _option("schedule", step.kind, opts) == "polynomial" \
                        and opts[key] < init_s:
                    return (f"{step.name}: {key} {opts[key]} is below initial_sparsity {init_s}; "
                            f"the polynomial schedule only increases sparsity")
        return None

    # --- fine-tuning -------------------------------------------------------------------------------------

    def finetune(self, request: FineTuneRequest) -> FineTuned:
        tensorflow(request.threads)
        k = keras()
        if reason := self.steps_reason(request.steps, request.source.format, request.task):
            raise ValueError(reason)
        plan = _plan(request.steps)
        k.utils.set_random_seed(request.seed)
        model = request.source.load()
        splits: dict[float, TrainingData] = {}
        facts: dict[str, Any] = {"kinds": [s.kind for s in request.steps], "phases": [p for p, _, _ in plan],
                                 "loss": LOSSES[request.task]}
        done: list[str] = []
        pruned: set[str] = set()
        for phase, kind, opts in plan:
            fraction = float(_option("fraction", kind, opts))
            if fraction not in splits:
                inputs, labels = request.train(fraction)
                splits[fraction] = training_data(inputs, labels, request.source.inputs, request.task, model)
            data = splits[fraction]
            epochs = _phase_epochs(phase, kind, opts)
            lr = float(_option("lr", kind, opts))
            batch = int(_option("batch_size", kind, opts))
            n_epochs, per_epoch = _schedule(len(data), batch, epochs)
            info: dict[str, Any] = {"epochs": epochs, "samples": len(data), "lr": lr, "batch_size": batch,
                                    "steps": n_epochs * per_epoch}
            if phase == "prune":
                model, loss, extra = self._prune(model, kind, opts, data, lr, batch, n_epochs, per_epoch,
                                                 request.seed)
                pruned = set(extra.pop("pruned_layers"))
            elif phase == "cluster":
                model, loss, extra = self._cluster(model, kind, opts, data, lr, batch, n_epochs, per_epoch,
                                                   request.seed, preserve_sparsity="prune" in done)
            else:
                model, loss, extra = self._qat(model, done, data, lr, batch, n_epochs, per_epoch,
                                               request.seed)
            info.update(extra)
            info["final_loss"] = loss
            facts[phase] = info
            done.append(phase)
        last = plan[-1][0]
        facts["final_loss"] = facts[last]["final_loss"]
        facts["epochs"] = sum(facts[p]["epochs"] for p in done)
        facts["samples"] = max(facts[p]["samples"] for p in done)
        facts["lr"] = facts[done[0]]["lr"]
        if "prune" in facts:
            facts["target_sparsity"] = facts["prune"]["target_sparsity"]
        if "cluster" in facts:
            facts["target_clusters"] = facts["cluster"]["clusters"]
        kernels = stored_kernels(model)
        facts.update(weight_stats(kernels))
        if "cluster" in facts and "qat" in facts:
            # Per-channel 8-bit quantisation scales each output channel of a conv kernel on its own, so the
            # float kernels of a CQAT model keep <= clusters values per output channel, not per tensor.
            facts["clusters_per_channel"] = max(len(np.unique(c)) for k_ in kernels for c in np.moveaxis(k_, -1, 0))
        if pruned:  # sparsity over the kernels tfmot pruned (layers below min_weights stay dense)
            facts["pruned_kernel_sparsity"] = weight_stats(stored_kernels(model, pruned))["sparsity"]
        out = Path(request.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if "qat" in done:
            model.save(out / QAT_FILE)
            return FineTuned(QAT_FILE, QAT_FORMAT, facts)
        model.save(out / "model.keras")
        return FineTuned("model.keras", "keras", facts)

    def _prune(self, model: Any, kind: str, opts: dict[str, Any], data: TrainingData, lr: float,
               batch: int, n_epochs: int, per_epoch: int, seed: int) -> tuple[Any, float, dict[str, Any]]:
        k, tfmot = keras(), tfmot_module()
        sp = tfmot.sparsity.keras
        total = n_epochs * per_epoch
        # Masks are updated every `frequency` steps (about 20 updates in all). The polynomial schedule reaches its
        # final sparsity at end_step, two thirds of the way, so the last cut has a third of the steps to recover.
        frequency = max(1, total // 20)
        end_step = frequency * max(0, round(total * RAMP_SHARE) // frequency)
        schedule_name = _option("schedule", kind, opts)
        initial = float(_option("initial_sparsity", kind, opts))
        final = float(_option("final_sparsity", kind, opts))
        targets = {"conv": float(opts.get("conv_sparsity", final)), "linear": float(opts.get("linear_sparsity", final))}

        def schedule(target: float) -> Any:
            if schedule_name == "constant":
                return sp.ConstantSparsity(target, begin_step=0, frequency=frequency)
            return sp.PolynomialDecay(min(initial, target), target, begin_step=0, end_step=end_step,
                                      frequency=frequency)

        min_weights = int(_option("min_weights", kind, opts))
        sizes = {layer.name: int(np.prod(layer.kernel.shape)) for layer in model.layers if is_weighted(layer)}
        names = [name for name, size in sizes.items() if size >= min_weights]
        if not names:
            raise ValueError(f"prune: no Conv/Dense kernel has min_weights ({min_weights}) weights or more (the "
                             f"largest has {max(sizes.values(), default=0)}); lower min_weights")

        def wrap(layer: Any) -> Any:
            if layer.name not in names:
                return layer
            target = targets["linear"] if isinstance(layer, k.layers.Dense) else targets["conv"]
            return sp.prune_low_magnitude(layer, pruning_schedule=schedule(target))

        wrapped = k.models.clone_model(model, clone_function=wrap)
        _copy_weights(model, wrapped)
        loss = fit(wrapped, data, lr, batch, n_epochs, per_epoch, seed, [sp.UpdatePruningStep()])
        # The optimizer's last step may move masked weights off zero: apply the final masks before stripping.
        for layer in wrapped.layers:
            for weight, mask, _ in getattr(layer, "pruning_vars", ()):
                weight.assign(weight * mask)
        stripped = sp.strip_pruning(wrapped)
        extra = {"schedule": schedule_name, "target_sparsity": final, "pruned_layers": names,
                 "dense_layers": {n: size for n, size in sizes.items() if n not in names},
                 "min_weights": min_weights, "mask_updates_every_steps": frequency}
        if schedule_name == "polynomial":
            extra["initial_sparsity"] = initial
        if "conv_sparsity" in opts or "linear_sparsity" in opts:
            extra.update(conv_sparsity=targets["conv"], linear_sparsity=targets["linear"])
        return stripped, loss, extra

    def _cluster(self, model: Any, kind: str, opts: dict[str, Any], data: TrainingData, lr: float,
                 batch: int, n_epochs: int, per_epoch: int, seed: int,
                 preserve_sparsity: bool) -> tuple[Any, float, dict[str, Any]]:
        k, tfmot = keras(), tfmot_module()
        cl = tfmot.clustering.keras
        clusters = int(_option("clusters", kind, opts))
        init = _option("init", kind, opts)
        params = {"number_of_clusters": clusters,
                  "cluster_centroids_init": getattr(cl.CentroidInitialization, INITS[init])}
        if preserve_sparsity:
            params["preserve_sparsity"] = True

        def wrap(layer: Any) -> Any:
            return cl.cluster_weights(layer, **params) if is_weighted(layer) else layer

        wrapped = k.models.clone_model(model, clone_function=wrap)
        _copy_weights(model, wrapped)
        loss = fit(wrapped, data, lr, batch, n_epochs, per_epoch, seed)
        stripped = cl.strip_clustering(wrapped)
        return stripped, loss, {"clusters": clusters, "init": init, "preserve_sparsity": preserve_sparsity}

    def _qat(self, model: Any, done: list[str], data: TrainingData, lr: float, batch: int,
             n_epochs: int, per_epoch: int, seed: int) -> tuple[Any, float, dict[str, Any]]:
        k, tfmot = keras(), tfmot_module()
        qk = tfmot.quantization.keras
        from tensorflow_model_optimization.python.core.quantization.keras.default_8bit import (
            default_8bit_quantize_registry as registry_module,
        )

        registry = registry_module.Default8BitQuantizeRegistry()
        combine = tfmot.experimental.combine
        if "cluster" in done:
            scheme = combine.Default8BitClusterPreserveQuantizeScheme(preserve_sparsity="prune" in done)
            scheme_name = "cluster_preserve" + ("+sparsity" if "prune" in done else "")
        elif "prune" in done:
            scheme, scheme_name = combine.Default8BitPrunePreserveQuantizeScheme(), "prune_preserve"
        else:
            scheme, scheme_name = qk.default_8bit.Default8BitQuantizeScheme(), "default_8bit"
        float_layers = []

        def annotate(layer: Any) -> Any:
            if registry.supports(layer):
                return qk.quantize_annotate_layer(layer)
            float_layers.append(f"{layer.name} ({type(layer).__name__})")
            return layer

        annotated = k.models.clone_model(model, clone_function=annotate)
        _copy_weights(model, annotated)
        with qk.quantize_scope(qat_custom_objects()):
            quantized = qk.quantize_apply(annotated, scheme)
        started = init_activation_ranges(quantized, observed_ranges(model, data))
        loss = fit(quantized, data, lr, batch, n_epochs, per_epoch, seed)
        extra: dict[str, Any] = {"scheme": scheme_name, "ranges_started_from_data": len(started)}
        if float_layers:
            extra["float_layers"] = float_layers  # tfmot's 8-bit registry does not support them: left float
        return quantized, loss, extra


def _copy_weights(source: Any, target: Any) -> None:
    """Copy weights layer by layer into a clone whose layers may be wrapped (prune/cluster/quantize wrappers)."""
    for src, dst in zip(source.layers, target.layers, strict=True):
        inner = getattr(dst, "layer", dst)
        if src.weights:
            inner.set_weights(src.get_weights())


def _schedule(samples: int, batch: int, epochs: float) -> tuple[int, int]:
    """(epochs run, steps per epoch) for a possibly fractional number of epochs; integers are exact."""
    per_full_epoch = max(1, math.ceil(samples / batch))
    n_epochs = max(1, math.ceil(epochs))
    per_epoch = max(1, round(epochs * per_full_epoch / n_epochs))
    return n_epochs, per_epoch
