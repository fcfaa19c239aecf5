"""TfmotTrainer with the real tensorflow-model-optimization on a tiny Keras model (a few seconds per kind); a
classifier fine-tuned on cross-entropy, and a model with two inputs and two outputs."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("tensorflow_model_optimization")

import tiny_keras

from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.sources.keras_qat import QAT_FORMAT, load_qat
from bench_matrix.sources.tensorflow import keras, tensorflow
from bench_matrix.strategies.base import FineTuneRequest, weight_stats
from bench_matrix.strategies.tfmot import TfmotTrainer
from bench_matrix.strategies.tfmot_models import stored_kernels
from bench_matrix.tensors import TensorSpec, take

IMAGE = (TensorSpec("image", tiny_keras.INPUT_SHAPE),)
FAST = {"fraction": 1.0, "batch_size": 32, "lr": 1e-3, "min_weights": 0}  # the tiny kernels hold 32 to 1152 weights


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    path = tiny_keras.save_trained(tmp_path_factory.mktemp("src") / "tiny.keras", epochs=60)
    return SourceModel("tiny", "tensorflow", "keras", path, _sha(path), IMAGE)


@pytest.fixture(scope="module")
def data() -> tuple[np.ndarray, np.ndarray]:
    x = tiny_keras.images(128, 7)
    return x, tiny_keras.colour_balance(x)


def _run(source: SourceModel, data: Any, out: Path, *steps: tuple[str, dict[str, Any]],
         task: str = "regression") -> Any:
    x, y = data
    inputs = x if isinstance(x, dict) else {"image": x}
    specs = tuple(StrategySpec(f"{kind}_{i}", kind, {**FAST, **opts}) for i, (kind, opts) in enumerate(steps))
    request = FineTuneRequest(source=source, steps=specs, out_dir=out,
                              train=lambda f: (take(inputs, slice(0, int(len(y) * f))), y[:int(len(y) * f)]),
                              threads=2, seed=0, task=task)
    return TfmotTrainer().finetune(request)


def _per_channel_clusters(kernels: list[np.ndarray]) -> int:
    """Most distinct values in one output channel of any kernel: CQAT's per-channel 8-bit quantisation of conv
    kernels keeps the clusters within each channel (each channel's centroids are scaled on their own)."""
    return max(len(np.unique(c)) for k in kernels for c in np.moveaxis(k, -1, 0))


def _load(out: Path, result: Any) -> Any:
    path = out / result.file
    assert path.exists() and path.parent == out
    if result.format == QAT_FORMAT:
        return load_qat(path)
    assert result.format == "keras"
    return keras().models.load_model(path, compile=False)


def test_prune_reaches_target_and_leaves_the_source_alone(source: SourceModel, data: Any, tmp_path: Path) -> None:
    before = _sha(source.path)
    result = _run(source, data, tmp_path, ("prune", {"final_sparsity": 0.6, "initial_sparsity": 0.3,
                                                     "epochs": 2}))
    assert _sha(source.path) == before == source.sha256
    kernels = stored_kernels(_load(tmp_path, result))
    # Every Conv2D/Dense kernel is pruned (BatchNormalization has no kernel and is not counted), and tfmot
    # keeps exactly round(0.6 * size) zeros per kernel, so the measured sparsity reaches the target (a
    # rounding tolerance of one weight per kernel).
    assert len(kernels) == 4 and result.facts["pruned_kernel_sparsity"] == result.facts["sparsity"]
    tol = len(kernels) / sum(k.size for k in kernels)
    assert weight_stats(kernels)["sparsity"] >= 0.6 - tol
    assert result.facts["sparsity"] == pytest.approx(weight_stats(kernels)["sparsity"])
    assert result.facts["target_sparsity"] == 0.6 and result.facts["prune"]["schedule"] == "polynomial"
    assert np.isfinite(result.facts["final_loss"])


def _mse(model: Any, data: Any) -> float:
    x, y = data
    return float(np.mean((model.predict(x, verbose=0) - y) ** 2))


def test_prune_keeps_small_kernels_dense_and_the_model_useful(source: SourceModel, data: Any,
                                                               tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("prune", {"final_sparsity": 0.8, "epochs": 10, "min_weights": 500}))
    model = _load(tmp_path, result)
    # Kernels: conv 216 and 576 weights, dense 1152 and 32; those under 500 weights stay dense.
    sizes = {layer.name: int(layer.kernel.shape.num_elements()) for layer in model.layers if hasattr(layer, "kernel")}
    small = {name for name, size in sizes.items() if size < 500}
    assert result.facts["prune"]["dense_layers"] == {name: sizes[name] for name in small} and len(small) == 2
    pruned = [layer.kernel.numpy() for layer in model.layers if layer.name in set(sizes) - small]
    dense = [layer.kernel.numpy() for layer in model.layers if layer.name in small]
    assert all(np.count_nonzero(k) == k.size for k in dense)
    assert weight_stats(pruned)["sparsity"] >= 0.8 - 2 / sum(k.size for k in pruned)
    assert result.facts["pruned_kernel_sparsity"] == pytest.approx(weight_stats(pruned)["sparsity"])
    # The record's sparsity is over every kernel: the dense ones pull it below the target.
    assert result.facts["sparsity"] == pytest.approx(weight_stats(pruned + dense)["sparsity"])
    assert result.facts["sparsity"] < 0.8
    # Still useful: the source is at about 0.05 of the mean predictor's MSE; the pruned model stays under 0.1.
    _, y = data
    assert _mse(model, data) < 0.1 * float(np.mean((y - y.mean(axis=0)) ** 2))


def test_prune_with_no_kernel_of_min_weights_says_so(source: SourceModel, data: Any, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"no Conv/Dense kernel has min_weights \(5000\).*largest has 1152"):
        _run(source, data, tmp_path, ("prune", {"min_weights": 5000, "epochs": 1}))


def test_qat_activation_ranges_start_from_the_data(source: SourceModel, data: Any, tmp_path: Path) -> None:
    """tfmot starts ranges at [-6, 6] and its EMA barely moves in a short fine-tuning; ours start at the data's."""
    result = _run(source, data, tmp_path, ("qat", {"epochs": 1, "lr": 1e-9}))
    model, float_model = _load(tmp_path, result), source.load()
    x, _ = data
    probe = keras().Model(float_model.inputs, [layer.output for layer in float_model.layers])
    observed = {layer.name: np.asarray(out) for layer, out in zip(float_model.layers, probe(x), strict=True)}
    checked = 0
    for layer in model.layers:
        ranges = {v.name.split("/")[-1].split(":")[0]: float(v.numpy()) for v in layer.weights
                  if "post_activation" in v.name}
        if not ranges:
            continue
        seen = observed[layer.layer.name]
        span = max(seen.max(), 0) - min(seen.min(), 0)
        assert ranges["post_activation_max"] == pytest.approx(max(seen.max(), 0), abs=0.1 * float(span))
        assert ranges["post_activation_min"] == pytest.approx(min(seen.min(), 0), abs=0.1 * float(span))
        checked += 1
    assert checked == 4 and result.facts["qat"]["ranges_started_from_data"] == 8
    # With no learning, QAT costs only the 8-bit rounding: outputs within a few steps of the float model's.
    assert np.max(np.abs(model.predict(x, verbose=0) - float_model.predict(x, verbose=0))) < 0.05


def test_cluster_limits_distinct_values(source: SourceModel, data: Any, tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("cluster", {"clusters": 4, "epochs": 1}))
    kernels = stored_kernels(_load(tmp_path, result))
    assert len(kernels) == 4 and all(len(np.unique(k)) <= 4 for k in kernels)
    assert result.facts["clusters"] <= 4 and result.facts["target_clusters"] == 4


def test_qat_round_trips_and_converts_to_int8(source: SourceModel, data: Any, tmp_path: Path) -> None:
    tf = tensorflow()
    result = _run(source, data, tmp_path, ("qat", {"epochs": 1}))
    assert result.format == QAT_FORMAT and (tmp_path / result.file).is_dir()
    model = _load(tmp_path, result)
    # The leading BatchNormalization is not in tfmot's 8-bit registry: it stays float, and the facts say so.
    assert any("BatchNormalization" in name for name in result.facts["qat"]["float_layers"])
    assert np.all(np.isfinite(model.predict(data[0][:32], verbose=0)))
    # One epoch of QAT at lr 1e-3 on this data matches the float source's MSE or improves on it (0.024 vs 0.030).
    assert _mse(model, data) <= 1.1 * _mse(source.load(), data)
    converter = tf.lite.TFLiteConverter.from_keras_model(model)
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    interpreter = tf.lite.Interpreter(model_content=converter.convert())
    dtypes = {d["dtype"] for d in interpreter.get_tensor_details()}
    assert np.int8 in dtypes


def test_pqat_preserves_sparsity(source: SourceModel, data: Any, tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("pqat", {"final_sparsity": 0.5, "prune_epochs": 1, "qat_epochs": 1}))
    kernels = stored_kernels(_load(tmp_path, result))
    tol = len(kernels) / sum(k.size for k in kernels)
    assert result.format == QAT_FORMAT and weight_stats(kernels)["sparsity"] >= 0.5 - tol
    assert result.facts["qat"]["scheme"] == "prune_preserve"


def test_cqat_preserves_clusters(source: SourceModel, data: Any, tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("cqat", {"clusters": 4, "cluster_epochs": 1, "qat_epochs": 1}))
    kernels = stored_kernels(_load(tmp_path, result))
    assert result.format == QAT_FORMAT and _per_channel_clusters(kernels) <= 4
    assert result.facts["clusters_per_channel"] == _per_channel_clusters(kernels)


def test_pcqat_preserves_both(source: SourceModel, data: Any, tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("pcqat", {"final_sparsity": 0.5, "clusters": 4, "prune_epochs": 1,
                                                      "cluster_epochs": 1, "qat_epochs": 1}))
    kernels = stored_kernels(_load(tmp_path, result))
    tol = len(kernels) / sum(k.size for k in kernels)
    assert weight_stats(kernels)["sparsity"] >= 0.5 - tol
    assert _per_channel_clusters(kernels) <= 4


def test_steps_prune_then_qat_is_pqat(source: SourceModel, data: Any, tmp_path: Path) -> None:
    result = _run(source, data, tmp_path, ("prune", {"final_sparsity": 0.5, "schedule": "constant", "epochs": 1}),
                  ("qat", {"epochs": 1}))
    assert result.format == QAT_FORMAT and result.facts["phases"] == ["prune", "qat"]
    assert result.facts["qat"]["scheme"] == "prune_preserve"
    kernels = stored_kernels(_load(tmp_path, result))
    assert weight_stats(kernels)["sparsity"] >= 0.5 - len(kernels) / sum(k.size for k in kernels)


def test_strategies_from_one_source_do_not_interact(source: SourceModel, data: Any, tmp_path: Path) -> None:
    source_zeros = weight_stats(stored_kernels(source.load()))["sparsity"]
    _run(source, data, tmp_path / "p", ("prune", {"final_sparsity": 0.8, "epochs": 1}))
    result = _run(source, data, tmp_path / "c", ("cluster", {"clusters": 8, "epochs": 1}))
    # Clustering a pruned model would leave ~80 % zeros; from the pristine source, at most one of 8 centroids
    # may sit at zero by chance, far below that.
    assert result.facts["sparsity"] < max(0.3, source_zeros + 0.2)


def test_steps_reason() -> None:
    t = TfmotTrainer()
    assert t.steps_reason((StrategySpec("p", "prune", {}),), "keras") is None
    assert "Keras" in t.steps_reason((StrategySpec("p", "prune", {}),), "onnx")
    assert "global" in t.steps_reason((StrategySpec("p", "prune", {"scope": "global"}),), "keras")
    assert "order" in t.steps_reason((StrategySpec("q", "qat", {}), StrategySpec("p", "prune", {})), "h5")
    assert "at most once" in t.steps_reason((StrategySpec("q", "pqat", {}), StrategySpec("p", "qat", {})), "h5")
    assert "ptq_static" in t.steps_reason((StrategySpec("s", "ptq_static", {}),), "keras")
    assert t.steps_reason((StrategySpec("p", "prune", {}), StrategySpec("c", "cluster", {}),
                           StrategySpec("q", "qat", {})), "saved_model") is None
    assert t.probe() is None and "tensorflow-model-optimization" in t.versions()


def _keras_source(model: Any, path: Path, inputs: tuple[TensorSpec, ...]) -> SourceModel:
    model.save(path)
    return SourceModel(path.stem, "tensorflow", "keras", path, _sha(path), inputs)


def _classifier(last: str = "logits") -> Any:
    """16x16x3 images -> 3 classes: logits, or probabilities from a softmax activation, layer or
    Activation."""
    k = keras()
    k.utils.set_random_seed(0)
    head = {"logits": [k.layers.Dense(3)], "dense_softmax": [k.layers.Dense(3, activation="softmax")],
            "softmax_layer": [k.layers.Dense(3), k.layers.Softmax()],
            "activation": [k.layers.Dense(3), k.layers.Activation("softmax")]}[last]
    return k.Sequential([k.layers.Input(tiny_keras.INPUT_SHAPE),
                         k.layers.Conv2D(8, 3, strides=2, activation="relu"), k.layers.Flatten(),
                         k.layers.Dense(16, activation="relu"), *head])


def _class_images(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """NHWC noise images whose brightest channel is their class (int64 ids 0..2)."""
    rng = np.random.default_rng(seed)
    y = rng.integers(0, 3, n)
    x = rng.random((n, *tiny_keras.INPUT_SHAPE)).astype(np.float32) * 0.6
    x[np.arange(n), ..., y] += 0.4
    return x, y.astype(np.int64)


def _entropy_and_accuracy(model: Any, x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    logits = model.predict(x, verbose=0)
    shifted = logits - logits.max(axis=1, keepdims=True)
    log_p = shifted - np.log(np.exp(shifted).sum(axis=1, keepdims=True))
    return float(-log_p[np.arange(len(y)), y].mean()), float((logits.argmax(axis=1) == y).mean())


def test_classifier_is_pruned_on_cross_entropy(tmp_path: Path) -> None:
    source = _keras_source(_classifier(), tmp_path / "classifier.keras", IMAGE)
    held_out = _class_images(128, 1)
    before, chance = _entropy_and_accuracy(source.load(), *held_out)
    result = _run(source, _class_images(256, 0), tmp_path / "out",
                  ("prune", {"final_sparsity": 0.5, "schedule": "constant", "epochs": 3, "lr": 1e-2}),
                  task="classification")
    after, accuracy = _entropy_and_accuracy(_load(tmp_path / "out", result), *held_out)
    assert result.facts["loss"] == "cross_entropy" and result.facts["sparsity"] >= 0.5 - 0.01
    assert after < 0.5 * before and accuracy >= 0.9 > chance + 0.3, (before, after, chance, accuracy)


@pytest.mark.parametrize(("last", "from_logits"), [("logits", True), ("dense_softmax", False),
                                                   ("softmax_layer", False), ("activation", False)])
def test_cross_entropy_is_on_logits_unless_the_model_ends_in_softmax(last: str, from_logits: bool) -> None:
    from bench_matrix.strategies.keras_fit import _objective, training_data

    model = _classifier(last)
    x, y = _class_images(4, 0)
    data = training_data({"image": x}, y, IMAGE, "classification", model)
    loss, _, targets = _objective(model, data)
    assert loss.get_config()["from_logits"] is from_logits and targets.dtype == np.int64


TWO_INPUTS = (TensorSpec("features", (tiny_keras.FEATURES,)),
              TensorSpec("ids", (tiny_keras.TOKENS,), "int64"))


@pytest.fixture(scope="module")
def two_io(tmp_path_factory: pytest.TempPathFactory) -> tuple[SourceModel, dict[str, np.ndarray], np.ndarray]:
    """The two-input, two-output model, and labels: zeta's column, then alpha's two, from both inputs."""
    source = _keras_source(tiny_keras.two_inputs_two_outputs(), tmp_path_factory.mktemp("two") / "two.keras",
                           TWO_INPUTS)
    inputs = tiny_keras.token_data(256, 0)
    features, ids = inputs["features"], inputs["ids"]
    y = np.concatenate([features[:, :1], np.maximum(features[:, 1:3], 0) + ids[:, :2] / 10], axis=1)
    return source, {"ids": ids, "features": features}, y.astype(np.float32)  # the data in another order


def _two_io_mse(model: Any, inputs: dict[str, np.ndarray], y: np.ndarray) -> float:
    zeta, alpha = model.predict([inputs["features"], inputs["ids"]], verbose=0)
    return float(np.mean((np.concatenate([zeta, alpha], axis=1) - y) ** 2))


def test_two_input_two_output_model_is_pruned_on_every_output(two_io: Any, tmp_path: Path) -> None:
    source, inputs, y = two_io
    result = _run(source, (inputs, y), tmp_path, ("prune", {"final_sparsity": 0.5, "schedule": "constant",
                                                            "epochs": 10, "lr": 1e-2}))
    model = _load(tmp_path, result)
    assert result.facts["loss"] == "mse" and result.facts["sparsity"] == pytest.approx(0.5, abs=0.01)
    # the MSE over both outputs' columns falls from the random model's (about 1.7) to a tenth of it
    assert _two_io_mse(model, inputs, y) < 0.1 * _two_io_mse(source.load(), inputs, y)
    assert result.facts["final_loss"] == pytest.approx(_two_io_mse(model, inputs, y), rel=0.5)


def test_two_input_qat_keeps_the_model_close(two_io: Any, tmp_path: Path) -> None:
    source, inputs, y = two_io
    result = _run(source, (inputs, y), tmp_path, ("qat", {"epochs": 1, "lr": 1e-9}))
    floats = result.facts["qat"]["float_layers"]  # names are numbered per process
    assert len(floats) == 1 and floats[0].endswith("(Embedding)"), floats
    model = _load(tmp_path, result)
    assert _two_io_mse(model, inputs, y) == pytest.approx(_two_io_mse(source.load(), inputs, y), rel=0.1)


def test_qat_ranges_of_each_float_input_start_from_its_data() -> None:
    """The second of two inputs feeds a Dense directly: its QuantizeLayer starts at that input's range."""
    from bench_matrix.sources.keras_qat import tfmot_module
    from bench_matrix.strategies.keras_fit import training_data
    from bench_matrix.strategies.tfmot_ranges import init_activation_ranges, observed_ranges

    k = keras()
    ids = k.layers.Input((tiny_keras.TOKENS,), dtype="int64", name="ids")
    features = k.layers.Input((tiny_keras.FEATURES,), name="features")
    embedded = k.layers.GlobalAveragePooling1D()(k.layers.Embedding(tiny_keras.VOCABULARY, 4)(ids))
    model = k.Model([ids, features], k.layers.Add()([k.layers.Dense(4)(features), embedded]))
    qk = tfmot_module().quantization.keras
    annotated = k.models.clone_model(
        model, clone_function=lambda layer: qk.quantize_annotate_layer(layer) if isinstance(
            layer, k.layers.Dense) else layer)
    quantized = qk.quantize_apply(annotated)
    data = tiny_keras.token_data(64, 1)
    data["features"] *= 0.5
    specs = tuple(reversed(TWO_INPUTS))
    set_ranges = init_activation_ranges(quantized, observed_ranges(
        model, training_data(data, np.zeros((64, 4), np.float32), specs, "regression", model)))
    layer = next(layer for layer in quantized.layers if type(layer).__name__ == "QuantizeLayer")
    ranges = {v.name.split("/")[-1].split(":")[0][-3:]: float(v.numpy()) for v in layer.weights
              if v.name.endswith(("_min:0", "_max:0"))}
    assert ranges == {"min": pytest.approx(float(data["features"].min())),
                      "max": pytest.approx(float(data["features"].max()))}
    assert f"{layer.name}/{layer.name}_min" in set_ranges


def test_steps_reason_refuses_a_task_without_labels() -> None:
    trainer, prune = TfmotTrainer(), (StrategySpec("p", "prune", {}),)
    assert trainer.steps_reason(prune, "keras", "none") == "fine-tuning needs labels; the task is none"
    assert trainer.steps_reason(prune, "keras", "classification") is None
