"""Third-party backends for the vocabulary tests: a target (npu), a precision (int4) and options (hint,
streams) bench-matrix does not know; installed as a .dist-info with entry points."""

from __future__ import annotations

from bench_matrix.backends.base import Backend, Session, Support


class NpuBackend(Backend):
    """Declares an NPU at int4 with a performance hint; never converts (the tests only plan)."""

    name = "npu_rt"
    description = "test plugin with its own target, precision and option"
    supports = (Support(("onnx",), ("none",), ("fp32", "int4"), ("cpu", "npu")),)
    options = {"hint": {"enum": ["latency", "throughput"], "description": "what the runtime optimises for"},
               "streams": {"type": "integer", "minimum": 1, "maximum": 16}}

    def probe(self, target: str, precision: str) -> str | None:
        return "no NPU on this machine" if target == "npu" else None

    def convert(self, request):
        raise NotImplementedError("the vocabulary tests never convert")

    def load(self, artifact_dir, meta, target, precision, threads) -> Session:
        raise NotImplementedError("the vocabulary tests never load")


class BadOptionsBackend(NpuBackend):
    """Declares an option whose schema is not a JSON Schema: its options cannot be checked."""

    name = "bad_opts"
    options = {"hint": {"type": "fancy"}}
