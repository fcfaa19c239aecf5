"""Third-party backends named like the built-in onnxruntime one, installed as .dist-info with entry points:
one that declares it replaces the built-in backend, and one that does not."""

from __future__ import annotations

from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend


class ReplacesOnnxRuntime(OnnxRuntimeBackend):
    """The built-in backend under its own name, declaring that it replaces it."""

    description = "a vendor's ONNX Runtime build, replacing the built-in backend"
    replaces = "onnxruntime"


class ClashesWithOnnxRuntime(OnnxRuntimeBackend):
    """The built-in backend under its own name, declaring nothing."""

    description = "a vendor's ONNX Runtime build that does not say it replaces the built-in backend"
