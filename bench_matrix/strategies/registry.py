"""Trainers are found only through the `bench_matrix.trainers` entry-point group, built-in or plugin."""

from __future__ import annotations

from importlib.metadata import entry_points

from bench_matrix.strategies.base import Trainer

ENTRY_POINT_GROUP = "bench_matrix.trainers"


class TrainerLoadError(Exception):
    """A registered trainer could not be imported or is not a Trainer."""


def trainer_names() -> list[str]:
    return sorted({ep.name for ep in entry_points(group=ENTRY_POINT_GROUP)})


def load_trainer(name: str) -> Trainer:
    """Import and instantiate one registered trainer."""
    eps = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not eps:
        raise TrainerLoadError(f"no trainer named {name!r} is installed (installed: "
                               f"{', '.join(trainer_names())})")
    try:
        cls = eps[0].load()
        trainer = cls()
    except Exception as exc:  # a broken plugin must not take the tool down
        raise TrainerLoadError(f"trainer {name!r} ({eps[0].value}) failed to load: "
                               f"{type(exc).__name__}: {exc}") from exc
    if not isinstance(trainer, Trainer):
        raise TrainerLoadError(f"trainer {name!r} ({eps[0].value}) is not a bench_matrix Trainer")
    return trainer
