"""Trainers are found only through the `bench_matrix.trainers` entry-point group, built-in or plugin."""

from __future__ import annotations

from bench_matrix.registry import Group, PluginError
from bench_matrix.strategies.base import Trainer


class TrainerLoadError(PluginError):
    """A registered trainer could not be imported or created, or is not a Trainer."""


TRAINERS = Group("bench_matrix.trainers", "trainer", Trainer, TrainerLoadError)


def trainer_names() -> list[str]:
    return TRAINERS.names()


def load_trainer(name: str) -> Trainer:
    """Import and instantiate one registered trainer."""
    return TRAINERS.load(name)
