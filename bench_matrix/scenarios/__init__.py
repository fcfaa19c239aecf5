"""Scenarios: what a measure job measures with a loaded session (base.py). The core ones (base.CORE: latency)
run for every cell; the registered ones (the `bench_matrix.scenarios` entry points: registry.scenarios) are
selected per cell by their own top-level matrix section."""
