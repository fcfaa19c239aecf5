"""A third-party backend package for the tests: installed as a real .dist-info with an entry point."""

from __future__ import annotations

import os
import shutil

from bench_matrix.plugin import Backend, Session, Support


class CrashyBackend(Backend):
    """Converts by copying, then aborts the process when loading: a runtime that crashes."""

    name = "crashy"
    description = "test plugin whose runtime crashes"
    supports = (Support(("pytorch",), ("none",), ("fp32",), ("cpu",)),)

    def convert(self, request):
        shutil.copy(request.source.path, request.out_dir / "model.bin")
        return {}

    def load(self, artifact_dir, meta, target, precision, threads) -> Session:
        os.abort()


class BrokenBackend(Backend):
    """Forgets to implement `load`: it cannot be instantiated, which must not take other backends down."""

    name = "broken"
    description = "test plugin missing an abstract method"
    supports = (Support(("pytorch",), ("none",), ("fp32",), ("cpu",)),)

    def convert(self, request):
        return {}
