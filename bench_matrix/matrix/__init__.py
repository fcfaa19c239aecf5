"""The matrix file: its schema, loading with located errors, and expansion into cells."""

from bench_matrix.matrix.load import load_matrix
from bench_matrix.matrix.spec import DatasetSpec, Matrix, ModelSpec, Settings
from bench_matrix.strategy import StrategySpec

__all__ = ["DatasetSpec", "Matrix", "ModelSpec", "Settings", "StrategySpec", "load_matrix"]
