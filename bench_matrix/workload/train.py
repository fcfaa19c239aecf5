"""Train a built-in reference model on the training split (deterministic from the seed): MSE against the label
columns (regression) or cross-entropy of the logits with int64 class ids (classification)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.matrix.spec import TrainingSpec
from bench_matrix.phases import Epochs
from bench_matrix.tensors import Inputs, count

TASKS = ("regression", "classification")


def train_torch(factory: str, inputs: Inputs, y: np.ndarray, spec: TrainingSpec, seed: int, out: Path,
                threads: int, task: str = "regression") -> dict[str, Any]:
    """Adam on the task's loss for spec.epochs; save the state_dict to `out`; return training facts."""
    import torch

    from bench_matrix.sources.pytorch import build_from_factory

    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    model = build_from_factory(factory).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=spec.lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=spec.epochs)
    xts = [torch.from_numpy(x) for x in inputs.values()]  # in the model's input order
    yt = torch.from_numpy(_labels(y, task))
    loss_of = torch.nn.functional.cross_entropy if task == "classification" else torch.nn.functional.mse_loss
    generator = torch.Generator().manual_seed(seed)
    begin = time.perf_counter()
    losses = []
    epochs = Epochs(spec.epochs)
    for _ in range(spec.epochs):
        order = torch.randperm(len(yt), generator=generator)
        total = 0.0
        for start in range(0, len(order), spec.batch_size):
            idx = order[start:start + spec.batch_size]
            optimiser.zero_grad(set_to_none=True)
            loss = loss_of(model(*(x[idx] for x in xts)), yt[idx])
            loss.backward()
            optimiser.step()
            total += loss.item() * len(idx)
        scheduler.step()
        losses.append(total / len(yt))
        epochs.ended(len(losses), losses[-1])
    train_s = time.perf_counter() - begin
    with open(out, "wb") as file:  # a file, not a path: torch names the archive's entries after a path's
        torch.save(model.eval().state_dict(), file)  # stem, here the partial name with the pid in it
    return {"epochs": spec.epochs, "batch_size": spec.batch_size, "lr": spec.lr, "train_s": round(train_s, 2),
            "final_train_loss": losses[-1], "train_samples": count(inputs), "threads": threads}


def train_keras(builtin: str, inputs: Inputs, y: np.ndarray, spec: TrainingSpec, seed: int, out: Path,
                threads: int, task: str = "regression") -> dict[str, Any]:
    """The Keras twin of train_torch (Adam, cosine-decayed learning rate, the task's loss); saves a .keras
    file."""
    from bench_matrix.sources.tensorflow import epoch_phases, keras, tensorflow
    from bench_matrix.workload.pilotnet_keras import BUILDERS

    tf = tensorflow(threads)
    k = keras()
    k.utils.set_random_seed(seed)
    tf.config.experimental.enable_op_determinism()
    model = BUILDERS[builtin]()
    steps = spec.epochs * -(-count(inputs) // spec.batch_size)
    loss = k.losses.SparseCategoricalCrossentropy(from_logits=True) if task == "classification" else "mse"
    model.compile(optimizer=k.optimizers.Adam(k.optimizers.schedules.CosineDecay(spec.lr, steps)), loss=loss)
    begin = time.perf_counter()
    x = list(inputs.values())
    history = model.fit(x[0] if len(x) == 1 else x, _labels(y, task), batch_size=spec.batch_size,
                        epochs=spec.epochs, shuffle=True, verbose=0, callbacks=[epoch_phases(spec.epochs)])
    train_s = time.perf_counter() - begin
    inference = BUILDERS[builtin]()  # uncompiled: the .keras file holds the model, not Adam's two moments
    inference.set_weights(model.get_weights())
    inference.save(out)  # Keras picks the format from the file ending
    return {"epochs": spec.epochs, "batch_size": spec.batch_size, "lr": spec.lr, "train_s": round(train_s, 2),
            "final_train_loss": float(history.history["loss"][-1]), "train_samples": count(inputs),
            "threads": threads}


def _labels(y: np.ndarray, task: str) -> np.ndarray:
    """int64 class ids (N,) for classification, float32 label columns (N, K) for regression."""
    if task not in TASKS:
        raise ValueError(f"a built-in model is trained for regression or classification, not task {task!r}")
    return y.astype(np.int64).reshape(len(y)) if task == "classification" else y.astype(np.float32)
