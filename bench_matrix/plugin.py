"""The plugin API: all of bench-matrix a backend or trainer plugin may use (docs/plugins.md lists it)."""

from bench_matrix.backend import DEVICES, Backend, ConvertRequest, Session, Support
from bench_matrix.hardware import cuda_mismatch_reason, no_gpu_reason, precision_reason
from bench_matrix.measure.env import installed_versions
from bench_matrix.measure.work import onnx_work
from bench_matrix.op_profile import KINDS, PRECISIONS, OperatorTime, Profile, kind_of
from bench_matrix.phases import Epochs
from bench_matrix.sources import ModelFileError, SourceModel
from bench_matrix.sources.forward_call import for_inputs
from bench_matrix.sources.fx_trace import fx_prepare
from bench_matrix.sources.model_io import read_inputs
from bench_matrix.sources.onnx_file import load_onnx
from bench_matrix.sources.pytorch import quiet_torch, use_engine
from bench_matrix.sources.tensorflow import epoch_phases, keras, tensorflow, thread_settings
from bench_matrix.strategies.base import FineTuned, FineTuneRequest, Trainer, training_arrays, weight_stats
from bench_matrix.strategy import QAT_KINDS, StrategySpec
from bench_matrix.tensors import Inputs, TensorSpec, concrete, count, example_inputs, flat_outputs, \
    random_inputs, resize, specs_from_list, specs_to_list, take

__all__ = [
    # backends
    "Backend", "ConvertRequest", "DEVICES", "QAT_KINDS", "Session", "StrategySpec", "Support",
    # profiles (Session.profile)
    "KINDS", "OperatorTime", "PRECISIONS", "Profile", "kind_of",
    # the work of an inference (a conversion's `work`)
    "onnx_work",
    # trainers
    "Epochs", "FineTuneRequest", "FineTuned", "Trainer", "epoch_phases", "training_arrays", "weight_stats",
    # source models
    "ModelFileError", "SourceModel", "for_inputs", "fx_prepare", "keras", "load_onnx", "quiet_torch",
    "read_inputs", "tensorflow", "thread_settings", "use_engine",
    # tensors
    "Inputs", "TensorSpec", "concrete", "count", "example_inputs", "flat_outputs", "random_inputs", "resize",
    "specs_from_list", "specs_to_list", "take",
    # the machine
    "cuda_mismatch_reason", "installed_versions", "no_gpu_reason", "precision_reason",
]
