"""bench-matrix: one declarative matrix of model optimisations, measured honestly."""

__version__ = "0.1.0"
