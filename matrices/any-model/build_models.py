"""Build the five models of matrices/any-model.yaml and write them next to this script (deterministic).

    .venv/bin/python matrices/any-model/build_models.py

The three bend classifiers are fitted briefly on the training split of the built-in driving_bends workload,
read through bench-matrix's own data preparation, so they see exactly what the matrix evaluates them on:
  mobilenet.keras  Keras MobileNetV2 (alpha 0.35, weights=None), NHWC
  resnet.pt        state_dict of models.SmallResNet (a factory), NCHW
  cnn.onnx         models.plain_cnn exported with torch.onnx, dynamic batch axis, NCHW
and two more:
  encoder.pt       state_dict of models.Encoder (seeded, untrained; task none on synthetic token ids)
  tabular.keras    a Keras MLP fitted on tabular.npz, a 12-feature regression table written here
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
os.environ.setdefault("TF_USE_LEGACY_KERAS", "1")  # Keras 2 (tf_keras), as bench-matrix loads models

import models  # noqa: E402  (models.py, next to this script)
from bench_matrix.data import load_split, prepare  # noqa: E402
from bench_matrix.matrix.spec import DatasetSpec, Preprocess  # noqa: E402
from bench_matrix.workspace import Workspace  # noqa: E402

SEED = 0
WORKSPACE = Workspace(HERE.parents[1] / ".bench-matrix" / "any-model")  # shares the run's dataset cache
# The matrix's top-level dataset; tests/test_any_model_matrix.py checks the two agree.
BENDS = DatasetSpec(kind="builtin", builtin="driving_bends", task="classification", samples=2000, circuits=20,
                    seed=SEED, preprocess=Preprocess(scale=1.0 / 255.0))
TABULAR_ROWS, TABULAR_FEATURES = 2000, 12


def bends(layout: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The matrix's train and test splits as a model in `layout` takes them: (images, classes)."""
    directory, _ = prepare(BENDS, WORKSPACE)
    out = {}
    for split in ("train", "test"):
        inputs, labels = load_split(directory, split, BENDS.preprocess, layout)
        out[split] = (inputs["x"], labels)
    return out


def fit_torch(module, data: dict[str, tuple[np.ndarray, np.ndarray]], epochs: int, lr: float) -> float:
    """Fit a classifier with Adam, cross-entropy and a cosine schedule; return its test top-1."""
    import torch

    x, y = (torch.from_numpy(a) for a in data["train"])
    optimiser = torch.optim.Adam(module.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, epochs * -(-len(x) // 32))
    order = np.random.default_rng(SEED)
    for _ in range(epochs):
        module.train()
        for batch in np.array_split(order.permutation(len(x)), -(-len(x) // 32)):
            optimiser.zero_grad()
            loss = torch.nn.functional.cross_entropy(module(x[batch]), y[batch])
            loss.backward()
            optimiser.step()
            schedule.step()
    module.eval()
    with torch.no_grad():
        logits = torch.cat([module(torch.from_numpy(part)) for part in np.array_split(data["test"][0], 8)])
    return float((logits.argmax(1).numpy() == data["test"][1]).mean())


def build_resnet(data: dict[str, tuple[np.ndarray, np.ndarray]]) -> float:
    import torch

    torch.manual_seed(SEED)
    module = models.resnet()
    top1 = fit_torch(module, data, epochs=8, lr=3e-3)
    torch.save(module.state_dict(), HERE / "resnet.pt")
    return top1


def build_cnn(data: dict[str, tuple[np.ndarray, np.ndarray]]) -> float:
    import torch

    torch.manual_seed(SEED)
    module = models.plain_cnn()
    top1 = fit_torch(module, data, epochs=8, lr=3e-3)
    example = torch.from_numpy(data["test"][0][:1])
    torch.onnx.export(module, (example,), str(HERE / "cnn.onnx"), dynamo=False, opset_version=17,
                      input_names=["image"], output_names=["logits"],
                      dynamic_axes={"image": {0: "batch"}, "logits": {0: "batch"}})
    return top1


def build_encoder() -> None:
    import torch

    torch.manual_seed(SEED)
    torch.save(models.encoder().state_dict(), HERE / "encoder.pt")


def seed_keras():
    import tensorflow as tf
    import tf_keras

    tf_keras.utils.set_random_seed(SEED)
    tf.config.experimental.enable_op_determinism()
    return tf_keras


def build_mobilenet(data: dict[str, tuple[np.ndarray, np.ndarray]]) -> float:
    keras = seed_keras()
    model = keras.applications.MobileNetV2(input_shape=data["train"][0].shape[1:], alpha=0.35, weights=None,
                                           classes=models.CLASSES, classifier_activation=None)
    for layer in model.layers:  # Keras applications use 0.999: too slow for moving statistics of a brief fit
        if isinstance(layer, keras.layers.BatchNormalization):
            layer.momentum = 0.9
    epochs, steps = 6, -(-len(data["train"][1]) // 32)
    schedule = keras.optimizers.schedules.CosineDecay(3e-3, epochs * steps)
    model.compile(optimizer=keras.optimizers.Adam(schedule),
                  loss=keras.losses.SparseCategoricalCrossentropy(from_logits=True), metrics=["accuracy"])
    model.fit(*data["train"], batch_size=32, epochs=epochs, verbose=0)
    save_without_optimizer(keras, model, HERE / "mobilenet.keras")
    return float(model.evaluate(*data["test"], verbose=0)[1])


def save_without_optimizer(keras, model, path: Path) -> None:
    """Save an uncompiled copy: the file keeps the weights, not Adam's moments (a third of its size)."""
    copy = keras.models.clone_model(model)
    copy.set_weights(model.get_weights())
    copy.save(path)


def write_tabular() -> None:
    """2000 rows of 12 standard-normal features; the target mixes sine, product, square and abs terms."""
    rng = np.random.default_rng(SEED)
    x = rng.standard_normal((TABULAR_ROWS, TABULAR_FEATURES)).astype(np.float32)
    y = (np.sin(2 * x[:, 0]) + x[:, 1] * x[:, 2] + 0.5 * x[:, 3] ** 2 - np.abs(x[:, 4]) + 0.3 * x[:, 5]
         + 0.1 * rng.standard_normal(TABULAR_ROWS))
    np.savez(HERE / "tabular.npz", features=x, y=y[:, None].astype(np.float32))


def build_tabular() -> tuple[float, float]:
    """Fit the MLP on the training split of tabular.npz; return its and the mean predictor's test MSE."""
    write_tabular()
    spec = DatasetSpec(kind="npz", paths=(HERE / "tabular.npz",), task="regression")
    directory, info = prepare(spec, WORKSPACE)
    (x, y), (test_x, test_y) = (load_split(directory, split, spec.preprocess, "nhwc")
                                for split in ("train", "test"))
    keras = seed_keras()
    features = keras.Input(shape=(TABULAR_FEATURES,), name="features")
    hidden = keras.layers.Dense(64, activation="relu")(features)
    hidden = keras.layers.Dense(64, activation="relu")(hidden)
    model = keras.Model(features, keras.layers.Dense(1, name="target")(hidden), name="tabular_mlp")
    model.compile(optimizer=keras.optimizers.Adam(1e-3), loss="mse")
    model.fit(x["features"], y, batch_size=32, epochs=60, verbose=0)
    save_without_optimizer(keras, model, HERE / "tabular.keras")
    return float(model.evaluate(test_x["features"], test_y, verbose=0)), info["mean_predictor_mse"]


def main() -> None:
    import torch

    torch.set_num_threads(os.cpu_count() or 1)
    torch.use_deterministic_algorithms(True)
    start = time.perf_counter()
    nchw, nhwc = bends("nchw"), bends("nhwc")
    majority = float(np.mean(nchw["test"][1] == np.bincount(nchw["train"][1]).argmax()))
    print(f"driving_bends test split: {len(nchw['test'][1])} samples, majority class top-1 {majority:.3f}")
    for name, build in (("resnet.pt", lambda: build_resnet(nchw)), ("cnn.onnx", lambda: build_cnn(nchw)),
                        ("mobilenet.keras", lambda: build_mobilenet(nhwc))):
        began = time.perf_counter()
        print(f"{name}: test top-1 {build():.3f} ({time.perf_counter() - began:.0f} s)", flush=True)
    build_encoder()
    print("encoder.pt: seeded, untrained (task none)")
    mse, mean_mse = build_tabular()
    print(f"tabular.keras: test MSE {mse:.3f} (mean predictor {mean_mse:.3f})")
    print(f"built in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
