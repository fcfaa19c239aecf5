"""Load PyTorch source models safely: TorchScript, torch.export programs, or a factory plus weights."""

from __future__ import annotations

import importlib
import io
import sys
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from bench_matrix.sources import ModelFileError
from bench_matrix.sources.forward_call import for_inputs
from bench_matrix.sources.torch_files import RE_EXPORT, brief, check_export_archive, check_torchscript, \
    unpickling_cause

if TYPE_CHECKING:
    import torch

    from bench_matrix.sources import SourceModel

SAVE_WEIGHTS = "save the weights with torch.save(model.state_dict(), path)"
SHOWN_KEYS = 5  # keys listed in a state_dict mismatch before '... and N more'


def load_module(source: "SourceModel") -> "torch.nn.Module":
    """A fresh module in eval mode on the CPU; UserError when the file is unsafe or unreadable."""
    if source.format == "torchscript":
        return load_torchscript(source.path.read_bytes(), source.label)
    if source.format == "torch_export":  # exported in inference mode already; its module refuses .eval()
        return load_program(source.path.read_bytes(), source.label).module()
    if source.format == "state_dict":  # forward gets the inputs by name where they are named so
        module = build_from_factory(source.factory or "", source.python_path)
        load_weights(module, source)
        return for_inputs(module.eval(), [spec.name for spec in source.inputs])
    raise ValueError(f"{source.path}: format {source.format!r} is not a PyTorch format")


def load_torchscript(data: bytes, label: str) -> "torch.jit.ScriptModule":
    """The ScriptModule of a checked archive, loaded from the very bytes that were checked."""
    import torch

    check_torchscript(data, label)
    try:
        return torch.jit.load(io.BytesIO(data), map_location="cpu").eval()
    except RuntimeError as exc:
        raise ModelFileError(f"{label}: torch {torch.__version__} cannot load this TorchScript "
                             f"archive ({brief(exc)}); save it again with torch.jit.save of this torch "
                             f"version") from None


def load_program(data: bytes, label: str) -> "torch.export.ExportedProgram":
    """A checked torch.export archive's program, read by torch's archive loader, not torch.export.load (may
    unpickle without weights_only); guard code dropped (module() would exec it), shape-range guards kept."""
    import torch
    from torch.export.pt2_archive._package import load_pt2

    check_export_archive(data, label)
    try:
        program = load_pt2(io.BytesIO(data)).exported_programs.get("model")
    except Exception as exc:  # a malformed program: its JSON, a verifier's check, an unknown operator
        raise ModelFileError(f"{label}: torch {torch.__version__} cannot load this torch.export "
                             f"program ({brief(exc)}); {RE_EXPORT} of this torch version") from None
    if program is None:
        raise ModelFileError(f"{label}: holds no program named 'model' (the one torch.export.save "
                             f"writes); {RE_EXPORT}")
    program._guards_code = []
    return program


def load_weights(module: "torch.nn.Module", source: "SourceModel") -> None:
    """Load the weights file into the factory's module: weights_only, and every key must match."""
    import pickle

    import torch

    try:
        state = torch.load(str(source.path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise ModelFileError(f"{source.label}: the weights file holds pickled objects other than tensors "
                             f"({unpickling_cause(exc)}), and bench-matrix will not unpickle them (that "
                             f"could run code from the file); {SAVE_WEIGHTS}") from None
    except Exception as exc:  # empty, truncated or not a torch.save file: torch raises many kinds
        what = "the file is empty" if source.path.stat().st_size == 0 else brief(exc)
        raise ModelFileError(f"{source.label}: is not a weights file torch.load can read ({what}); "
                             f"{SAVE_WEIGHTS}") from None
    where = f"{source.label} (weights for factory '{source.factory}')"
    if not isinstance(state, Mapping):
        raise ModelFileError(f"{where}: holds a {type(state).__name__}, not a state_dict; {SAVE_WEIGHTS}")
    expected = module.state_dict().keys()
    missing = [k for k in expected if k not in state]
    unexpected = [str(k) for k in state if k not in expected]
    if missing or unexpected:
        keys = "; ".join(_keys(what, found) for what, found in (("missing", missing),
                                                                ("unexpected", unexpected)) if found)
        raise ModelFileError(f"{where}: the state_dict does not match the module the factory builds: {keys}; "
                             f"save model.state_dict() of the module this factory builds, or name the "
                             f"factory that built these weights")
    try:
        module.load_state_dict(state)
    except (RuntimeError, TypeError, ValueError) as exc:  # shapes that differ, values that are not tensors
        reason = "; ".join(line.strip() for line in str(exc).splitlines()[1:] if line.strip())[:600]
        raise ModelFileError(f"{where}: the state_dict does not fit the module the factory builds: "
                             f"{reason or brief(exc)}") from None


def _keys(what: str, keys: list[str]) -> str:
    """'missing keys a, b, c ... and 7 more'."""
    more = f" ... and {len(keys) - SHOWN_KEYS} more" if len(keys) > SHOWN_KEYS else ""
    return f"{what} keys {', '.join(keys[:SHOWN_KEYS])}{more}"


def build_from_factory(factory: str, python_path: tuple[str, ...] = ()) -> "torch.nn.Module":
    """Call 'package.module:function' (with the matrix's python_path on sys.path) to build a module."""
    import torch

    for entry in reversed(python_path):
        if entry not in sys.path:
            sys.path.insert(0, entry)
    module_name, _, attr = factory.partition(":")
    paths = f" (python_path: {', '.join(python_path)})" if python_path else ""
    try:
        imported = importlib.import_module(module_name)
    except Exception as exc:  # ImportError, or any error the module raises while it is imported
        raise ModelFileError(f"cannot import factory '{factory}': importing module '{module_name}' failed: "
                             f"{brief(exc)}{paths}") from None
    builder = getattr(imported, attr, None)
    if not callable(builder):
        found = "has no" if builder is None else f"has a {type(builder).__name__}, not a function, as"
        raise ModelFileError(f"cannot import factory '{factory}': module '{module_name}' "
                             f"({getattr(imported, '__file__', '?')}) {found} attribute '{attr}'")
    try:
        module: Any = builder()
    except Exception as exc:
        raise ModelFileError(f"calling factory '{factory}' failed: {brief(exc)}") from None
    if not isinstance(module, torch.nn.Module):
        raise ModelFileError(f"factory '{factory}' returned a {type(module).__name__}, not a "
                             f"torch.nn.Module; it must build and return the module whose state_dict the "
                             f"weights file holds")
    return module


def use_engine(engine: str | None = None) -> str:
    """Select the quantised engine (`engine`, or x86 where supported, else fbgemm) and return its name."""
    import torch

    supported = torch.backends.quantized.supported_engines
    engine = engine or ("x86" if "x86" in supported else "fbgemm")
    if engine not in supported:
        raise RuntimeError(f"the artifact was quantised for torch's {engine!r} engine, which torch "
                           f"{torch.__version__} here lacks (it has {', '.join(supported)}); convert it again")
    torch.backends.quantized.engine = engine
    return engine


@contextmanager
def quiet_torch(captured: bool = False) -> Iterator[None]:
    """Silence torch's deprecation notices (torch.ao, torch.jit, TorchScript ONNX exporter); `captured`: also
    the tracer's tensor-to-Python notes, harmless once captured (FX-quantised scales, export shape guards)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
        warnings.filterwarnings("ignore", message="(reduce_range will be deprecated|no signature found for"
                                                  "|torch.quantize_per_tensor)")
        if captured:
            warnings.filterwarnings("ignore", message="Converting a tensor to a Python")
        yield


def count_params(module: "torch.nn.Module") -> int:
    """Number of parameter elements (ScriptModules included)."""
    return int(sum(p.numel() for p in module.parameters()))
