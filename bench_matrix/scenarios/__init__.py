"""Scenarios: what a measure job measures with a loaded session (base.py). `latency` runs for every cell; the
registered ones (the `bench_matrix.scenarios` entry points: bench_matrix.registry.scenarios) are selected per
cell by their own top-level matrix section."""
