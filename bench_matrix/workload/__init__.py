"""Synthetic workloads (data sets and simulators) used by the benchmarks."""
