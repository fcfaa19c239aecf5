"""Third-party backends for the vocabulary tests: a target (npu), a precision (int4) and options (hint,
streams) bench-matrix does not know, and a target on the CUDA device; installed as a .dist-info with entry
points."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.plugin import Backend, ConvertRequest, Session, Support

EMULATE = "NPU_RT_EMULATE"  # set: the "npu" target runs on ONNX Runtime's CPU provider (a stand-in device)


class NpuBackend(Backend):
    """Declares an NPU target, an int4 precision and its own options; runs ONNX files with ONNX Runtime on the
    CPU (and on the npu target when NPU_RT_EMULATE is set), at fp32 only."""

    name = "npu_rt"
    description = "test plugin with its own target, precision and option"
    supports = (Support(("onnx",), ("none",), ("fp32", "int4"), ("cpu", "npu")),)
    options = {"hint": {"enum": ["latency", "throughput"], "description": "what the runtime optimises for"},
               "streams": {"type": "integer", "minimum": 1, "maximum": 16}}

    def versions(self) -> dict[str, str]:
        return {"npu-rt": "0.1"}

    def probe(self, target: str, precision: str) -> str | None:
        if target == "npu" and not os.environ.get(EMULATE):
            return "no NPU on this machine"
        return "int4 needs an NPU compiler this test plugin lacks" if precision == "int4" else None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        shutil.copy2(request.source.path, request.out_dir / "model.onnx")
        return {"hint": request.options.get("hint", "latency"), "streams": request.options.get("streams", 1)}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        session = ort.InferenceSession(str(artifact_dir / "model.onnx"), options,
                                       providers=["CPUExecutionProvider"])
        return NpuSession(session, meta)


class NpuSession(Session):
    """One InferenceSession; records the options the conversion received."""

    def __init__(self, session: Any, meta: dict[str, Any]):
        self._session, self._meta = session, meta

    def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self._session.run(None, prepared)

    def info(self) -> dict[str, Any]:
        return {"hint": self._meta["hint"], "streams": self._meta["streams"]}


class FakeGpuBackend(NpuBackend):
    """Says its fake_gpu target runs on the CUDA device, and runs it on ONNX Runtime's CPU provider: what the
    measure job does on a GPU (end-to-end latency, the GPU's name and memory), on a machine without one."""

    name = "fake_gpu"
    supports = (Support(("onnx",), ("none",), ("fp32",), ("cpu", "fake_gpu")),)
    options = {}
    devices = {"fake_gpu": "cuda"}

    def probe(self, target: str, precision: str) -> str | None:
        return None


class BadOptionsBackend(NpuBackend):
    """Declares an option whose schema is not a JSON Schema: its options cannot be checked."""

    name = "bad_opts"
    options = {"hint": {"type": "fancy"}}
