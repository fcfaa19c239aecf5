"""What the TensorFlow-side backends share: library versions and the GPU probe of the TensorFlow build."""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from typing import Any

from bench_matrix.plugin import cuda_mismatch_reason, installed_versions, no_gpu_reason, precision_reason, \
    tensorflow

# Every distribution that installs the `tensorflow` module; those installed are reported.
DISTRIBUTIONS = ("tensorflow", "tensorflow-cpu", "tensorflow-gpu", "tf-keras")


def tf_versions(*extra: str) -> dict[str, str]:
    return installed_versions(*DISTRIBUTIONS, *extra)


def missing_tensorflow() -> str | None:
    """Why TensorFlow cannot be imported here, without importing it, or None."""
    if importlib.util.find_spec("tensorflow") is None:
        return ("TensorFlow is not installed: pip install tensorflow-cpu tf_keras at the versions "
                "requirements.lock pins (in a checkout: make setup; a GPU build: docs/gpu.md)")
    return None


def probe_tensorflow_gpu() -> str | None:
    """Why TensorFlow cannot run on an NVIDIA GPU here (every missing piece), or None."""
    reasons = [reason] if (reason := no_gpu_reason()) else []
    if missing := missing_tensorflow():
        return "; ".join([*reasons, missing])
    tf = tensorflow()
    build = tf.sysconfig.get_build_info()
    if not tf.test.is_built_with_cuda():
        reasons.append(f"this TensorFlow {tf.__version__} is a CPU-only build (tf.test.is_built_with_cuda() is "
                       f"False); install a CUDA build, e.g. tensorflow[and-cuda] on Linux")
    elif mismatch := cuda_mismatch_reason(f"TensorFlow {tf.__version__}", build.get("cuda_version")):
        reasons.append(mismatch)
    elif not reasons and not tf.config.list_physical_devices("GPU"):
        reasons.append(f"TensorFlow {tf.__version__} (built for CUDA {build.get('cuda_version')}, cuDNN "
                       f"{build.get('cudnn_version')}) sees no GPU: tf.config.list_physical_devices('GPU') is "
                       f"empty (driver too old, or CUDA libraries missing?)")
    return "; ".join(reasons) or None


def probe_tftrt(precision: str = "fp32") -> str | None:
    """Why TF-TRT cannot run `precision` here: no GPU, no CUDA build, not a TensorRT build, a GPU too old."""
    reasons = [reason] if (reason := probe_tensorflow_gpu()) else []
    if too_old := precision_reason(precision, f"TF-TRT {precision.upper()}"):
        reasons.append(too_old)
    if missing_tensorflow():
        return "; ".join(reasons)
    tf = tensorflow()
    if not tf.sysconfig.get_build_info().get("is_tensorrt_build", False):
        reasons.append(f"TensorFlow {tf.__version__} is not a TensorRT build "
                       f"(tf.sysconfig.get_build_info()['is_tensorrt_build'] is False): pip wheels never are; "
                       f"NVIDIA's TensorFlow containers (nvcr.io/nvidia/tensorflow) are")
    return "; ".join(reasons) or None


def keras_arguments(tensors: Sequence[Any]) -> Any:
    """What a Keras model is called with: its one input alone, or the list of its inputs in model.inputs order."""
    return tensors[0] if len(tensors) == 1 else list(tensors)
