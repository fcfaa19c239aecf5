"""Train a built-in reference model on the training split (deterministic from the seed)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from bench_matrix.matrix.spec import TrainingSpec


def train_torch(factory: str, x: np.ndarray, y: np.ndarray, spec: TrainingSpec, seed: int, out: Path,
                threads: int) -> dict[str, float]:
    """Adam on MSE for spec.epochs; save the state_dict to `out`; return training facts."""
    import torch

    from bench_matrix.sources.pytorch import build_from_factory

    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    model = build_from_factory(factory).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=spec.lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=spec.epochs)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    generator = torch.Generator().manual_seed(seed)
    begin = time.perf_counter()
    losses = []
    for _ in range(spec.epochs):
        order = torch.randperm(len(xt), generator=generator)
        total = 0.0
        for start in range(0, len(order), spec.batch_size):
            idx = order[start:start + spec.batch_size]
            optimiser.zero_grad(set_to_none=True)
            loss = torch.nn.functional.mse_loss(model(xt[idx]), yt[idx])
            loss.backward()
            optimiser.step()
            total += loss.item() * len(idx)
        scheduler.step()
        losses.append(total / len(xt))
    train_s = time.perf_counter() - begin
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    torch.save(model.eval().state_dict(), tmp)
    tmp.replace(out)
    return {"epochs": spec.epochs, "batch_size": spec.batch_size, "lr": spec.lr, "train_s": round(train_s, 2),
            "final_train_loss": losses[-1], "train_samples": int(len(x)), "threads": threads}


def train_keras(builtin: str, x: np.ndarray, y: np.ndarray, spec: TrainingSpec, seed: int, out: Path,
                threads: int) -> dict[str, float]:
    """The Keras twin of train_torch (Adam, cosine-decayed learning rate, MSE); saves a .keras file."""
    from bench_matrix.sources.tensorflow import keras, tensorflow
    from bench_matrix.workload.pilotnet_keras import BUILDERS

    tf = tensorflow(threads)
    k = keras()
    k.utils.set_random_seed(seed)
    tf.config.experimental.enable_op_determinism()
    model = BUILDERS[builtin]()
    steps = spec.epochs * -(-len(x) // spec.batch_size)
    model.compile(optimizer=k.optimizers.Adam(k.optimizers.schedules.CosineDecay(spec.lr, steps)), loss="mse")
    begin = time.perf_counter()
    history = model.fit(x, y, batch_size=spec.batch_size, epochs=spec.epochs, shuffle=True, verbose=0)
    train_s = time.perf_counter() - begin
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"tmp-{out.name}")  # Keras picks the format from the file ending
    inference = BUILDERS[builtin]()  # uncompiled: the .keras file holds the model, not Adam's two moments
    inference.set_weights(model.get_weights())
    inference.save(tmp)
    tmp.replace(out)
    return {"epochs": spec.epochs, "batch_size": spec.batch_size, "lr": spec.lr, "train_s": round(train_s, 2),
            "final_train_loss": float(history.history["loss"][-1]), "train_samples": int(len(x)),
            "threads": threads}
