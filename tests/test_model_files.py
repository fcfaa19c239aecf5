"""Hostile and broken PyTorch model and weights files (.pt2, TorchScript, state dicts with a factory):
nothing in them runs, and each refusal names the user's file and why."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Callable

import pytest
import torch

import tiny_models
from conftest import TESTS, cli
from model_file_helpers import (
    factory_source,
    make_source,
    payload_code,
    pickle_payload,
    refused,
    rewrite_zip,
)

from bench_matrix.sources import SourceModel

X = torch.from_numpy(tiny_models.images(4, 5))
MODEL_JSON = "models/model.json"


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, torch.nn.Module]:
    """tiny_models.fitted() exported with a dynamic batch (its shapes are then sympy expressions), saved."""
    module = tiny_models.fitted()
    path = tmp_path_factory.mktemp("exported") / "tiny.pt2"
    program = torch.export.export(module, (X,), dynamic_shapes=({0: torch.export.Dim("batch", max=64)},))
    torch.export.save(program, str(path))
    return path, module


def test_exported_program_loads_and_runs(exported: tuple[Path, torch.nn.Module]) -> None:
    path, module = exported
    with torch.no_grad():
        torch.testing.assert_close(make_source(path, "torch_export").load()(X), module(X))


def _pickled_weight(name: str, data: bytes, marker: Path) -> bytes:
    if name == "data/weights/model_weights_config.json":
        config = json.loads(data)
        next(iter(config["config"].values()))["use_pickle"] = True
        return json.dumps(config).encode()
    return pickle_payload(marker) if name == "data/weights/weight_0" else data


def _in_program(old: bytes, new: Callable[[Path], bytes]) -> Callable[[str, bytes, Path], bytes]:
    """A change that replaces `old` in the program's JSON."""
    return lambda name, data, marker: data.replace(old, new(marker)) if name == MODEL_JSON else data



HOSTILE_EXPORTS = {  # how a real archive is changed, entries added to it, and what the refusal says
    "pickled_weight": (_pickled_weight, {}, "stores weight '0.weight' as a pickled object"),
    "pickled_sample_inputs": (
        lambda n, d, m: pickle_payload(m) if n == "data/sample_inputs/model.pt" else d, {},
        "sample inputs (data/sample_inputs/model.pt) hold pickled objects"),
    "legacy_pickled_constants": (lambda n, d, m: d, {"data/constants/model.pt": b"TORCH"},
                                 "stores its constants as a pickle"),
    "shape_expression_code": (
        _in_program(b"Symbol(", lambda m: json.dumps(payload_code(m))[1:-1].encode() + b" or Symbol("), {},
        "is not plain arithmetic on symbols"),
    "file_operator": (_in_program(b"aten.relu.default", lambda m: b"aten.save.default"), {},
                      "operator torch.ops.aten.save.default, which reads or writes files"),
    "aot_compiled_code": (lambda n, d, m: d, {"data/aotinductor/model/model.so": b"\x7fELF"}, "AOTInductor"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_EXPORTS))
def test_hostile_exported_programs_are_refused(case: str, exported: tuple[Path, torch.nn.Module],
                                               tmp_path: Path) -> None:
    change, extra, expected = HOSTILE_EXPORTS[case]
    marker = tmp_path / "marker"
    added = {name: pickle_payload(marker) if data == b"TORCH" else data for name, data in extra.items()}
    path = rewrite_zip(exported[0], tmp_path / "hostile.pt2", lambda n, d: change(n, d, marker), added)
    refused(make_source(path, "torch_export"), f"{path}: ", expected, "torch.export.save")
    assert not marker.exists()


def test_guard_code_in_an_exported_program_never_runs(exported: tuple[Path, torch.nn.Module],
                                                      tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    code = json.dumps({"guards_code": [payload_code(marker)]})[1:-1].encode()
    guard = _in_program(b'"guards_code": []', lambda m: code)
    path = rewrite_zip(exported[0], tmp_path / "guarded.pt2", lambda n, d: guard(n, d, marker), {})
    assert payload_code(marker).encode() in zipfile.ZipFile(path).read(f"tiny/{MODEL_JSON}")
    with torch.no_grad():
        torch.testing.assert_close(make_source(path, "torch_export").load()(X), exported[1](X))
    assert not marker.exists()


class WritesOnLoad(torch.nn.Module):
    """A TorchScript module whose __setstate__ (run by torch.jit.load) writes a file with ATen's save."""

    def __init__(self, marker: str):
        super().__init__()
        self.marker, self.weight = marker, torch.ones(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.weight

    @torch.jit.export
    def __getstate__(self) -> tuple[str, torch.Tensor, bool]:
        return self.marker, self.weight, self.training

    @torch.jit.export
    def __setstate__(self, state: tuple[str, torch.Tensor, bool]) -> None:
        torch.save([state[1]], state[0])
        self.marker, self.weight, self.training = state


def test_torchscript_loads_and_one_that_writes_files_is_refused(tmp_path: Path) -> None:
    module = tiny_models.fitted()
    torch.jit.save(torch.jit.script(module), str(tmp_path / "tiny.pt"))
    with torch.no_grad():
        torch.testing.assert_close(make_source(tmp_path / "tiny.pt", "torchscript").load()(X), module(X))
    marker, hostile = tmp_path / "marker", tmp_path / "hostile.pt"
    torch.jit.save(torch.jit.script(WritesOnLoad(str(marker))), str(hostile))
    refused(make_source(hostile, "torchscript"), f"{hostile}: its TorchScript code",
            "calls operator 'save', which reads or writes files", "torch.jit.save")
    assert not marker.exists()


@pytest.mark.parametrize(("case", "expected"), [
    ("state_dict", "it is a torch.save file (a state_dict? give it as factory + weights"),
    ("truncated", "is not a TorchScript archive: RuntimeError: PytorchStreamReader failed reading zip"),
])
def test_torchscript_of_the_wrong_kind_is_named(case: str, expected: str, tmp_path: Path) -> None:
    path = tmp_path / "model.pt"
    torch.save(tiny_models.tiny().state_dict(), path)
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:300])
    refused(make_source(path, "torchscript"), f"{path}: ", expected)


FACTORIES = '''
import torch
def raises():
    raise RuntimeError("boom in the factory")
def not_a_module():
    return {"weight": 1}
def bigger():
    return torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Linear(8, 2))
def wider():
    return torch.nn.Sequential(torch.nn.Linear(4, 16))
'''


@pytest.fixture(scope="module")
def factories(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Factory modules (one whose import fails) and two weights files, in a python_path folder."""
    root = tmp_path_factory.mktemp("factories")
    (root / "model_file_factories.py").write_text(FACTORIES)
    (root / "model_file_broken.py").write_text("import no_such_module_anywhere\n")
    torch.save(torch.nn.Sequential(torch.nn.Linear(4, 8)).state_dict(), root / "small.pt")
    torch.save({"encoder.weight": torch.ones(8, 4), "0.weight": torch.ones(8, 4)}, root / "other.pt")
    return root


@pytest.mark.parametrize(("factory", "expected"), [
    ("model_file_factories:raises", "factory 'model_file_factories:raises' failed: RuntimeError: boom"),
    ("model_file_factories:not_a_module", "factory 'model_file_factories:not_a_module' returned a dict, "
                                          "not a torch.nn.Module"),
    ("model_file_factories:absent", "module 'model_file_factories'"),
    ("model_file_broken:build", "importing module 'model_file_broken' failed: ModuleNotFoundError"),
])
def test_factory_failures_say_the_factory_failed(factory: str, expected: str, factories: Path) -> None:
    refused(factory_source(factories / "small.pt", factory, factories), expected)


def test_weights_that_do_not_match_the_factory_name_file_factory_and_keys(factories: Path) -> None:
    small, bigger = factories / "small.pt", "model_file_factories:bigger"
    refused(factory_source(small, bigger, factories), f"{small} (weights for factory '{bigger}')",
            "missing keys 1.weight, 1.bias")
    refused(factory_source(small), "missing keys 0.running_mean, 0.running_var, 0.num_batches_tracked, "
                                   "1.weight, 1.bias ... and 6 more")
    refused(factory_source(factories / "other.pt", bigger, factories),
            "missing keys 0.bias, 1.weight, 1.bias; unexpected keys encoder.weight; save model.state_dict()")
    refused(factory_source(small, "model_file_factories:wider", factories),
            "does not fit the module the factory builds: size mismatch for 0.weight")


@pytest.mark.parametrize(("case", "expected"), [
    ("pickled_object", "holds pickled objects other than tensors (it refers to exec), and bench-matrix will "
                       "not unpickle them"),
    ("whole_module", "(it refers to torch.nn.modules.container.Sequential)"),
    ("empty", "is not a weights file torch.load can read (the file is empty)"),
    ("truncated", "is not a weights file torch.load can read"),
])
def test_unsafe_or_unreadable_weights_are_refused(case: str, expected: str, tmp_path: Path) -> None:
    path, marker = tmp_path / "weights.pt", tmp_path / "marker"
    torch.save(tiny_models.tiny() if case == "whole_module" else tiny_models.tiny().state_dict(), path)
    if case == "pickled_object":
        path.write_bytes(pickle_payload(marker))
    elif case in ("empty", "truncated"):
        path.write_bytes(path.read_bytes()[:0 if case == "empty" else 200])
    refused(factory_source(path), f"{path}: ", expected, "torch.save(model.state_dict(), path)")
    assert not marker.exists()


def test_messages_about_a_fine_tuned_copy_name_the_users_file(tmp_path: Path) -> None:
    (tmp_path / "copy.pt").write_bytes(b"")
    source = make_source(tmp_path / "copy.pt", "state_dict", factory="tiny_models:tiny",
                         python_path=(str(TESTS),), origin="/home/user/weights.pt")
    refused(source, f"/home/user/weights.pt (fine-tuned copy {tmp_path / 'copy.pt'}): is not a weights file")
    assert SourceModel.from_dict(source.to_dict()) == source



@pytest.mark.slow
def test_run_fails_broken_and_hostile_model_cells_naming_the_files(
        tiny_project: Path, exported: tuple[Path, torch.nn.Module]) -> None:
    marker = tiny_project / "marker"
    (tiny_project / "broken.onnx").write_bytes(b"\x08\x07garbage")
    rewrite_zip(exported[0], tiny_project / "hostile.pt2", lambda n, d: _pickled_weight(n, d, marker), {})
    (tiny_project / "m.yaml").write_text(
        "models:\n  - {name: broken, framework: onnx, file: broken.onnx}\n"
        "  - {name: hostile, framework: pytorch, file: hostile.pt2}\n"
        "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "axes: {backend: [onnxruntime], strategy: [none], precision: [fp32], target: [cpu]}\n"
        "settings: {timeout_s: 120}\n")
    run = cli(tiny_project, "run", "m.yaml")
    output = run.stdout + run.stderr
    assert run.returncode == 0 and "0 ok, 0 skipped, 2 failed" in output and "Traceback" not in output, output
    reasons = {r["cell"]["model"]: r["reason"]
               for r in json.loads(cli(tiny_project, "report", "--format", "json").stdout)["records"]}
    assert f"{tiny_project / 'broken.onnx'}: is not a valid ONNX model" in reasons["broken"]
    assert f"{tiny_project / 'hostile.pt2'}: it stores weight" in reasons["hostile"]
    assert "File \"" not in "".join(reasons.values()) and not marker.exists()
