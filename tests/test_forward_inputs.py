"""A factory's forward gets each input under its own name when the data's arrays are its parameters in
another order, or only some of them: in the eager baseline, TorchScript (traced and FX int8), ONNX export,
torch.export and fine-tuning; inputs that cannot be matched to its parameters are refused at plan time."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import forward_models  # noqa: E402
from conftest import FAST_SETTINGS, cli  # noqa: E402
from convert_helper import convert_with  # noqa: E402

import torch  # noqa: E402

from bench_matrix.backend import Backend  # noqa: E402
from bench_matrix.cli import main  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.forward_call import Parameter, call_problem  # noqa: E402
from bench_matrix.strategies.base import FineTuneRequest  # noqa: E402
from bench_matrix.strategies.torch_trainer import TorchTrainer  # noqa: E402
from bench_matrix.tensors import Inputs, TensorSpec, take  # noqa: E402
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend  # noqa: E402
from bench_matrix_backends.pytorch import PyTorchBackend  # noqa: E402
from bench_matrix_backends.torch_tensorrt import export  # noqa: E402
from bench_matrix_backends.torchscript import TorchScriptBackend  # noqa: E402

BACKENDS: dict[str, Backend] = {"pytorch": PyTorchBackend(), "torchscript": TorchScriptBackend(),
                                "onnxruntime": OnnxRuntimeBackend()}
CASES = [("pytorch", "none", "fp32"), ("torchscript", "none", "fp32"), ("torchscript", "ptq_dynamic", "int8"),
         ("torchscript", "ptq_static", "int8"), ("onnxruntime", "none", "fp32")]
ORDERS = ["cab", "ca"]  # all of forward's parameters in another order; a and c only (b left to its default)


def _source(folder: Path, names: str, state: Path | None = None, fmt: str = "state_dict") -> SourceModel:
    """forward_models.abc as a source whose inputs are the data's arrays `names`, in that order."""
    path = state or folder / "abc.pt"
    if state is None:
        torch.save(forward_models.abc().state_dict(), path)
    return SourceModel(name="abc", framework="pytorch", format=fmt, path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                       inputs=tuple(TensorSpec(name, (forward_models.WIDTH,)) for name in names),
                       factory="forward_models:abc", python_path=(str(TESTS),))


def _expected(inputs: Inputs) -> np.ndarray:
    """What the module computes when each array is passed under its own name."""
    with torch.inference_mode():
        return forward_models.abc()(**{k: torch.from_numpy(v) for k, v in inputs.items()}).numpy()


def _assert_close(got: np.ndarray, expected: np.ndarray, exact: bool = True) -> None:
    """Exact: equal but for summation order; else (int8, fine-tuned) off by under a quarter of the outputs'
    variance (an input passed as another parameter is off by about twice their variance)."""
    if exact:
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    else:
        assert np.mean((got - expected) ** 2) < 0.25 * expected.var()


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize(("backend", "kind", "precision"), CASES, ids=["-".join(c) for c in CASES])
def test_every_backend_passes_each_array_to_its_parameter(backend, kind, precision, order, tmp_path):
    source, inputs = _source(tmp_path, order), forward_models.arrays(order)
    meta = convert_with(inputs, BACKENDS[backend], source, tmp_path / "artifact", kind, precision)
    session = BACKENDS[backend].load(tmp_path / "artifact", meta, "cpu", precision, 1)
    (got,) = session.predict(inputs)
    _assert_close(got, _expected(inputs), exact=precision == "fp32")


def test_torch_export_takes_the_inputs_in_the_data_order(tmp_path):
    """As aot_inductor and torch_tensorrt export it: positionally, in the data's order."""
    source, inputs = _source(tmp_path, "cab"), forward_models.arrays("cab")
    program, _ = export(source.load(), source.inputs, 32, "cpu", torch.float32, 0)
    with torch.inference_mode():
        got = program.module()(*(torch.from_numpy(a) for a in inputs.values()))
    _assert_close(got.numpy(), _expected(inputs))


@pytest.mark.parametrize("kind", ["prune", "qat"])
def test_fine_tuning_trains_on_each_input_by_name_and_keeps_the_state_dict_keys(kind, tmp_path):
    """Labels are the module's own outputs: a fine-tuning that fed an input to another parameter would start
    (and end) far from them. The pruned state_dict loads into the factory's module again (same keys)."""
    source, inputs = _source(tmp_path, "cab"), forward_models.arrays("cab", n=64)
    labels = _expected(inputs)

    def train(fraction: float) -> tuple[Inputs, np.ndarray]:
        rows = slice(0, round(len(labels) * fraction))
        return take(inputs, rows), labels[rows]

    options = {"epochs": 1, "fraction": 1.0, "lr": 1e-6, **({"min_weights": 0} if kind == "prune" else {})}
    out = tmp_path / "tuned"
    out.mkdir()
    step = StrategySpec(kind, kind, options)
    tuned = TorchTrainer().finetune(FineTuneRequest(source, (step,), out, train, threads=1, seed=0))
    assert tuned.facts["final_loss"] < 0.25 * labels.var()
    module = _source(tmp_path, "cab", out / tuned.file, tuned.format).load()
    with torch.inference_mode():
        got = module(*(torch.from_numpy(a) for a in inputs.values())).numpy()
    _assert_close(got, labels, exact=False)


PLAN = ("models:\n  - {{name: abc, framework: pytorch, factory: 'forward_models:abc', weights: abc.pt, "
        "python_path: ['{tests}']{inputs}}}\n"
        "dataset: {{npz: data.npz, task: none}}\n"
        "axes: {{backend: [pytorch], strategy: [none], precision: [fp32], target: [cpu]}}\n")
DECLARED = ", inputs: [{name: c, shape: [4]}, {name: x, shape: [4]}, {name: b, shape: [4]}]"
FORWARD = "forward(a, b=…, c=…) of factory 'forward_models:abc'"
SOURCE = "(forward_models:abc + abc.pt) with data.npz"
REFUSALS = [
    ("cxb", "", f":2: models[0]: model abc {SOURCE}: the data's arrays (c, x, b) are not all named after the "
                f"parameters of {FORWARD}, and the order of a file's arrays does not say which is which; "
                f"rename the arrays after forward's parameters, or declare the model's `inputs:` in "
                f"forward's order"),
    ("cxb", DECLARED, f":2: models[0].inputs: model abc {SOURCE}: the declared inputs (c, x, b) would reach "
                      f"{FORWARD} by position, c as its parameter a; name every input after one of forward's "
                      f"parameters (each is then passed by name), or declare them in forward's order"),
    ("bc", "", f":2: models[0]: model abc {SOURCE}: {FORWARD} has no default for a, and the data's arrays "
               f"(b, c) hold none of that name; add it to the data"),
]


def _plan(folder: Path, arrays: str, inputs: str = "") -> int:
    """`bench-matrix plan` of forward_models.abc on data holding the arrays `arrays` (in that order)."""
    torch.save(forward_models.abc().state_dict(), folder / "abc.pt")
    np.savez(folder / "data.npz", **forward_models.arrays(arrays))
    (folder / "m.yaml").write_text(PLAN.format(tests=TESTS, inputs=inputs))
    return main(["--workspace", str(folder / "ws"), "plan", str(folder / "m.yaml")])


@pytest.mark.parametrize(("arrays", "inputs", "message"), REFUSALS, ids=["unnamed", "misplaced", "missing"])
def test_inputs_forward_cannot_take_are_refused_at_plan_time(arrays, inputs, message, tmp_path, capsys):
    assert _plan(tmp_path, arrays, inputs) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'm.yaml'}{message}" in err and "Traceback" not in err, err


@pytest.mark.parametrize(("arrays", "inputs"), [
    ("ca", ""),
    ("cab", ", inputs: [{name: c, shape: [4]}, {name: a, shape: [4]}, {name: b, shape: [4]}]"),
], ids=["some-arrays", "declared"])
def test_inputs_named_after_forwards_parameters_plan_in_any_order(arrays, inputs, tmp_path, capsys):
    assert _plan(tmp_path, arrays, inputs) == 0, capsys.readouterr()


def _params(*spec: str) -> tuple[Parameter, ...]:
    """'a' required, 'b=' with a default, '*args', '/a' positional-only."""
    kinds = {"*": "VAR_POSITIONAL", "/": "POSITIONAL_ONLY"}
    return tuple(Parameter(s.strip("*/="), kinds.get(s[0], "POSITIONAL_OR_KEYWORD"),
                           not s.startswith("*") and not s.endswith("=")) for s in spec)


@pytest.mark.parametrize(("params", "names", "declared", "refused"), [
    (("a", "b"), "ab", False, False),  # forward's order: positional, as always
    (("*args",), "xy", False, False),  # *args: the data's order, as always
    (("/a", "/b"), "xy", False, False),  # positional-only, other names: the data's order, as always
    (("/a", "/b"), "ba", False, True),  # positional-only, names swapped: b would be passed as a
    (("/a", "/b"), "ab", True, False),
    (("a", "b"), "xy", True, False),  # declared inputs not named after forward's parameters: declared order
    (("a", "b"), "xy", False, True),
    (("a", "b="), "x", False, False),  # one input: positional, as always
])
def test_which_signatures_are_refused(params, names, declared, refused):
    assert (call_problem("m:f", _params(*params), list(names), declared) is not None) == refused


KEYWORDS = ("models:\n  - {{name: kw, framework: pytorch, factory: 'forward_models:keywords', "
            "weights: kw.pt, python_path: ['{tests}']}}\n"
            "dataset: {{npz: data.npz, task: none, split: {{train: 0.5, calibration: 0.25, test: 0.25}}}}\n"
            "axes: {{backend: [pytorch, torchscript], strategy: [none, ptq_static], precision: [fp32, int8], "
            "target: [cpu]}}\n")
HUGGING_FACE = ("it is a Hugging Face transformers model, whose own tracer "
                "(transformers.utils.fx.symbolic_trace)")


@pytest.mark.slow
def test_a_hugging_face_style_forward_gets_its_inputs_by_name_in_every_trace(tmp_path):
    """forward(input_ids=None, attention_mask=None, inputs_embeds=None): FX would trace inputs_embeds as an
    input too (and the model refuses both); the int64 mask must stay unquantised in FX int8."""
    torch.save(forward_models.keywords().state_dict(), tmp_path / "kw.pt")
    np.savez(tmp_path / "data.npz", **forward_models.token_arrays())
    (tmp_path / "m.yaml").write_text(KEYWORDS.format(tests=TESTS) + FAST_SETTINGS)
    run = cli(tmp_path, "run", "m.yaml")
    assert run.returncode == 0, run.stderr
    records = json.loads(cli(tmp_path, "report", "--format", "json").stdout)["records"]
    cells = {(r["cell"]["backend"], r["cell"]["strategy"]): r for r in records}
    assert sorted(cells) == [("pytorch", "none"), ("torchscript", "none"), ("torchscript", "ptq_static")]
    for cell, record in cells.items():
        assert record["status"] == "ok", (cell, record["reason"])
        assert record["metrics"]["cosine_similarity"] > (0.99 if cell[1] == "ptq_static" else 0.999999)


@pytest.mark.parametrize("factory", ["branchy", "transformers_branchy"])
def test_a_module_no_tracer_can_trace_fails_in_one_line_naming_the_tracer(factory, tmp_path):
    path = tmp_path / "branchy.pt"
    torch.save(getattr(forward_models, factory)().state_dict(), path)
    specs = tuple(TensorSpec(name, a.shape[1:], "int64") for name, a in forward_models.token_arrays().items())
    source = SourceModel(name="branchy", framework="pytorch", format="state_dict", path=path, sha256="-",
                         inputs=specs, factory=f"forward_models:{factory}", python_path=(str(TESTS),))
    with pytest.raises(ValueError) as caught:
        convert_with(forward_models.token_arrays(), TorchScriptBackend(), source, tmp_path / "out",
                     "ptq_static", "int8")
    message = str(caught.value)
    assert "\n" not in message and message.startswith(
        "torch.ao.quantization prepare_fx: torch.fx cannot trace model branchy: TraceError: symbolically "
        "traced variables cannot be used as inputs to control flow"), message
    if factory == "branchy":
        assert "transformers" not in message
    elif importlib.util.find_spec("transformers") is None:
        missing = "cannot be imported here (ModuleNotFoundError: No module named 'transformers')"
        assert f"{HUGGING_FACE} {missing}" in message
    else:
        assert "transformers.utils.fx.symbolic_trace cannot trace it either" in message
