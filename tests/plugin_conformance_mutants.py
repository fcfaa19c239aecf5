"""Mutants of the built-in onnxruntime backend for the conformance kit's own tests: each copy breaks one rule
the way a plugin author could without noticing (a thread count echoed, outputs reversed, int8 claimed for an
fp32 program, a profile counting its operators many times over, stale outputs, fetch views of a reused buffer, the artifact kept in shared_dir, ragged batches
dropped), and must fail the kit with that rule."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.plugin import ConvertRequest, Profile, Session, StrategySpec, Support
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend, OrtSession

FP32 = Support(("onnx",), ("none",), ("fp32",), ("cpu",))
TILE = 8  # OrtTiles runs whole tiles of this many samples


class Mutant(OnnxRuntimeBackend):
    """The built-in backend on ONNX models on the CPU at fp32 only; each mutant overrides `session`."""

    name = "mutant"
    supports = (FP32,)
    baseline_for = ()
    devices = {}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return self.session(super().load(artifact_dir, meta, target, precision, threads))

    def session(self, loaded: Any) -> Session:
        return loaded


class OrtEchoesThreads(Mutant):
    """Runs on two threads whatever it is asked, and info() echoes the threads asked for."""

    name = "ort_echoes_threads"

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        class Echo(OrtSession):
            def info(self) -> dict[str, Any]:
                return {**super().info(), "threads": threads}

        loaded = OnnxRuntimeBackend.load(self, artifact_dir, meta, target, precision, 2)
        loaded.__class__ = Echo
        return loaded


class OrtReversed(Mutant):
    """fetch returns the outputs last first."""

    name = "ort_reversed"

    def session(self, loaded: Any) -> Session:
        class Reversed(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return super().fetch(outputs)[::-1]

        loaded.__class__ = Reversed
        return loaded


class OrtFakeInt8(Mutant):
    """Declares ptq_static int8 but converts (and serves) the fp32 model."""

    name = "ort_fake_int8"
    supports = (FP32, Support(("onnx",), ("ptq_static",), ("int8",), ("cpu",)))

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        fp32 = dataclasses.replace(request, step=StrategySpec("none", "none"), precision="fp32")
        return super().convert(fp32)


class OrtCountsTwice(Mutant):
    """profile() adds each operator's time once per call per operator it saw: many times the real time."""

    name = "ort_counts_twice"

    def session(self, loaded: Any) -> Session:
        class CountsTwice(OrtSession):
            def profile(self, prepared: dict[str, np.ndarray], calls: int) -> Profile:
                found = super().profile(prepared, calls)
                scale = 1000 * len(found.operators)
                return dataclasses.replace(found, operators=tuple(
                    dataclasses.replace(op, ms=op.ms * scale) for op in found.operators))

        loaded.__class__ = CountsTwice
        return loaded


class OrtStale(Mutant):
    """execute returns the outputs of the call before (its own, on the first call)."""

    name = "ort_stale"

    def session(self, loaded: Any) -> Session:
        class Stale(OrtSession):
            def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
                now = super().execute(prepared)
                before, self.kept = getattr(self, "kept", now), now
                return before

        loaded.__class__ = Stale
        return loaded


class OrtViews(Mutant):
    """fetch copies the outputs into buffers it keeps and returns views of them: the next call overwrites
    what the last one returned."""

    name = "ort_views"

    def session(self, loaded: Any) -> Session:
        class Views(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                buffers = getattr(self, "buffers", [np.empty(0, np.float32)] * len(outputs))
                self.buffers = [b if len(b) >= len(o) else np.empty((64, *o.shape[1:]), np.float32)
                                for b, o in zip(buffers, outputs)]
                for buffer, out in zip(self.buffers, outputs):
                    buffer[:len(out)] = out
                return [buffer[:len(out)] for buffer, out in zip(self.buffers, outputs)]

        loaded.__class__ = Views
        return loaded


class OrtPointer(Mutant):
    """Keeps the converted model in shared_dir and writes only a pointer to it into out_dir."""

    name = "ort_pointer"

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        meta = super().convert(request)
        kept = request.shared_dir / "artifact"
        shutil.rmtree(kept, ignore_errors=True)
        shutil.move(request.out_dir / meta["file"], kept)
        (request.out_dir / "pointer.json").write_text(json.dumps(str(kept)))
        return meta

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        kept = Path(json.loads((artifact_dir / "pointer.json").read_text()))
        return super().load(kept.parent, {**meta, "file": kept.name}, target, precision, threads)


class OrtTiles(Mutant):
    """Runs batches larger than a tile in whole tiles of TILE samples: the rest of a ragged batch is zeros."""

    name = "ort_tiles"

    def session(self, loaded: Any) -> Session:
        class Tiles(OrtSession):
            def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
                n = len(next(iter(prepared.values())))
                whole = n if n <= TILE else n - n % TILE
                outputs = super().execute({name: array[:whole] for name, array in prepared.items()})
                return [np.concatenate([o, np.zeros((n - whole, *o.shape[1:]), o.dtype)]) for o in outputs]

        loaded.__class__ = Tiles
        return loaded


# Each mutant's entry point, and the rules the kit must name for it (and no others).
MUTANTS = {cls.name: f"{__name__}:{cls.__name__}" for cls in (
    OrtEchoesThreads, OrtReversed, OrtFakeInt8, OrtCountsTwice, OrtStale, OrtViews, OrtPointer, OrtTiles)}
RULES = {"ort_echoes_threads": {"threads-as-asked"}, "ort_reversed": {"outputs-in-order"},
         "ort_fake_int8": {"int8-is-quantised", "profile-precisions-plausible"},
         "ort_counts_twice": {"profile-within-its-calls"}, "ort_stale": {"outputs-of-this-call"},
         "ort_views": {"fetch-returns-owned-arrays"}, "ort_pointer": {"artifact-lives-in-out_dir"},
         "ort_tiles": {"runs-any-batch"}}
