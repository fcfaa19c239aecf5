"""bench-matrix's backend conformance kit, a pytest plugin: enable it in a plugin package's tests with
`pytest_plugins = ["bench_matrix.conformance"]` and subclass BackendConformance naming the backends to check
(docs/plugins.md)."""

from bench_matrix.conformance.cases import TOLERANCES, RuleBroken, Tolerance
from bench_matrix.conformance.suite import BackendConformance

# Registering this package registers its hooks and fixture (kept apart, so that importing BackendConformance
# before the plugin is registered does not import them).
pytest_plugins = ["bench_matrix.conformance.plugin"]

__all__ = ["TOLERANCES", "BackendConformance", "RuleBroken", "Tolerance"]
