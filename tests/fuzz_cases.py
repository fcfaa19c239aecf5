"""Generators of broken and hostile matrix texts for test_fuzz_inputs.py, each with what its error message
must name, and what every case shares (fuzz_data_cases.py and fuzz_model_cases.py make the files); seeded."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml

TESTS = Path(__file__).resolve().parent
SEED = 11
SECRET = b"FUZZ-SECRET-MARKER-2468!"  # 24 bytes: the (3, 2) float32 weights an escaping ONNX model would read
Culprit = tuple[tuple[str, ...], ...]  # the message contains one alternative of every group ("re:" = a regex)


@dataclass(frozen=True)
class Case:
    """One generated input: `build(project)` writes it and returns what the test runs (a matrix text or bytes,
    or a model entry); `marker` is the file a payload in it would write."""

    id: str
    build: Callable[[Path], Any]
    culprit: Culprit = ()
    marker: str | None = None


class Payload:
    """Unpickling this writes `marker`, as a hostile pickle in a user's file would."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"import pathlib; pathlib.Path({self.marker!r}).write_text('pwned')",)


def markers(project: Path) -> Path:
    (project / "markers").mkdir(exist_ok=True)
    return project / "markers"


def onnx_model(location: str | None = None, dims: tuple = ("N", 3, 16, 16)) -> bytes:
    """A tiny ONNX model, (N,3,16,16) -> (N,2), its input's axes `dims` (a name or None: open); with
    `location`, its weights are external data there."""
    from onnx import TensorProto, helper, numpy_helper

    weights = numpy_helper.from_array(np.full((3, 2), 0.5, np.float32), "W")
    if location is not None:
        weights.ClearField("raw_data")
        weights.data_location = TensorProto.EXTERNAL
        for key, value in (("location", location), ("offset", "0"), ("length", str(len(SECRET)))):
            entry = weights.external_data.add()
            entry.key, entry.value = key, value
    nodes = [helper.make_node("ReduceMean", ["X"], ["M"], axes=[2, 3], keepdims=0),
             helper.make_node("MatMul", ["M", "W"], ["Y"])]
    graph = helper.make_graph(nodes, "tiny",
                              [helper.make_tensor_value_info("X", TensorProto.FLOAT, list(dims))],
                              [helper.make_tensor_value_info("Y", TensorProto.FLOAT, ["N", 2])], [weights])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    return model.SerializeToString()


def write_project(project: Path) -> Path:
    """tiny.onnx and data.npz (48 16x16 RGB images, 2 labels) in `project`."""
    (project / "tiny.onnx").write_bytes(onnx_model())
    rng = np.random.default_rng(SEED)
    np.savez(project / "data.npz", x=rng.integers(0, 256, (48, 16, 16, 3), dtype=np.uint8),
             y=rng.random((48, 2), np.float32))
    return project


# ---------------------------------------------------------------------------------------------- matrix files

BASE = {"models": [{"name": "tiny", "framework": "onnx", "file": "tiny.onnx"}],
        "dataset": {"npz": "data.npz", "split": {"train": 0.5, "calibration": 0.25, "test": 0.25}},
        "axes": {"backend": ["onnxruntime"], "strategy": ["none"], "precision": ["fp32"], "target": ["cpu"]},
        "settings": {"window_s": 0.01, "min_rounds": 2, "timing_budget_s": 0.05, "warmup_iterations": 2,
                     "warmup_s": 0.0, "batch_size": 8, "timeout_s": 120}}


def render(changes: tuple[tuple[tuple, Any], ...] = (), raw: str = "", at: tuple = ()) -> str:
    """The valid base matrix with `changes` (key path, value) applied, and raw YAML `raw` at key path `at`."""
    doc = copy.deepcopy(BASE)
    for path, value in changes + (((at, "__FUZZ__"),) if at else ()):
        node = doc
        for key in path[:-1]:
            node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
        node[path[-1]] = copy.deepcopy(value)
    return yaml.safe_dump(doc, sort_keys=False).replace("__FUZZ__", raw)


def key_path(dotted: str) -> tuple:
    return tuple(int(k) if k.isdigit() else k for k in dotted.split("."))


def shown(dotted: str) -> str:
    """'models.0.training.lr' -> 'models[0].training.lr', as messages show it (without a last list index)."""
    parts = key_path(dotted)
    text = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in parts)[1:]
    return text.rsplit("[", 1)[0] if isinstance(parts[-1], int) else text


def strategy(kind: str) -> tuple:
    return (("strategies",), {"s": {"kind": kind}}), (("axes", "strategy"), ["s"])


FACTORY = {"name": "tiny", "framework": "pytorch", "factory": "tiny_models:tiny", "weights": "tiny.pt",
           "python_path": [str(TESTS)]}
CONTEXT = {  # what a key needs around it to be valid
    "dataset.samples": ((("dataset",), {"builtin": "driving", "samples": 100, "circuits": 5}),),
    "dataset.preprocess.resize": ((("dataset", "preprocess"), {"resize": [16, 16]}),),
    "dataset.preprocess.mean": ((("dataset", "preprocess"), {"mean": [0.5], "std": [0.25]}),),
    "dataset.labels": ((("dataset", "labels"), {"offset": [0.0], "scale": [1.0]}),),
    "models.0.training": ((("models", 0, "training"), {}),),
    "models.0.weights": ((("models", 0), FACTORY),),
    "dataset.folder": ((("dataset",), {"folder": "rec"}),),
    "strategies.s.calibration_samples": strategy("ptq_static"), "strategies.s.clusters": strategy("cluster"),
    "strategies.s": strategy("prune"),
    "dataset.synthetic": ((("dataset",), {"synthetic": {"samples": 8}}),),
    "dataset.images": ((("dataset",), {"images": "imgs"}),),
    "dataset.preprocess.resize_shorter": ((("dataset", "preprocess"), {"resize_shorter": 16}),),
    "dataset.preprocess.center_crop": ((("dataset", "preprocess"), {"center_crop": [8, 8]}),),
    "models.0.inputs": ((("models", 0, "inputs"), [{"name": "X", "shape": [3, 16, 16], "range": [0, 1]}]),),
    "models.0.dataset": ((("models", 0, "dataset"), {"npz": "data.npz"}),),
}
CONTEXT["dataset.circuits"] = CONTEXT["dataset.samples"]
CONTEXT["dataset.preprocess.std"] = CONTEXT["dataset.preprocess.mean"]
CONTEXT["models.0.python_path"] = CONTEXT["models.0.weights"]


def context(dotted: str) -> tuple:
    return next((c for prefix, c in CONTEXT.items() if dotted.startswith(prefix)), ())


INTEGERS = ["settings.warmup_iterations", "settings.min_rounds", "settings.batch_size",
            "settings.threads", "settings.seed", "settings.eval_samples", "dataset.seed",
            "dataset.samples", "dataset.circuits", "dataset.preprocess.resize.0",
            "dataset.preprocess.crop.top", "models.0.training.epochs", "models.0.training.batch_size",
            "strategies.s.calibration_samples", "strategies.s.batch_size", "strategies.s.min_weights",
            "strategies.s.clusters", "dataset.synthetic.samples", "dataset.preprocess.resize_shorter",
            "dataset.preprocess.center_crop.1", "models.0.inputs.0.shape.0"]
# where a huge count means "all" or "none"; elsewhere it allocates or loops without end
HUGE_IS_MEANINGFUL = ["settings.eval_samples", "dataset.preprocess.crop.top", "strategies.s.min_weights",
                      "strategies.s.clusters"]
DURATIONS = ["settings.warmup_s", "settings.window_s", "settings.timing_budget_s", "settings.timeout_s",
             "strategies.s.epochs"]
REALS = ["strategies.s.lr", "strategies.s.fraction", "strategies.s.final_sparsity",
         "strategies.s.initial_sparsity", "models.0.training.lr", "dataset.preprocess.scale",
         "dataset.preprocess.mean.0", "dataset.preprocess.std.0", "dataset.labels.offset.0",
         "dataset.labels.scale.0", "dataset.split.train", "models.0.inputs.0.range.1", "settings.ci_target",
         "settings.memory_share"]
NOT_FINITE = {"nan": ".nan", "inf": ".inf", "neg_inf": "-.inf"}
BAD = {  # key -> its bad values
    **{k: {"whole_float": "2.0", "float_1e30": "1.0e+30", **NOT_FINITE, "string": "'8'", "bool": "true",
           "negative": "-3", **({} if k in HUGE_IS_MEANINGFUL else {"int_1e30": "1" + "0" * 30})}
       for k in INTEGERS},
    **{k: {**NOT_FINITE, "float_1e30": "1.0e+30", "negative": "-1.5", "string": "'1s'", "bool": "true"}
       for k in DURATIONS},
    **{k: {**NOT_FINITE, "string": "'x'", "bool": "false"} for k in REALS},
}


def value_cases() -> list[Case]:
    """Every key that takes a number, with every kind of number or non-number it must refuse."""
    return [Case(f"{key}={name}", lambda _p, t=render(context(key), raw, key_path(key)): t, ((shown(key),),))
            for key, values in BAD.items() for name, raw in values.items()]


PATHS = {"models.0.file": ".onnx", "models.0.weights": ".pt", "models.0.python_path.0": "",
         "dataset.npz": ".npz", "dataset.folder": "", "dataset.images": "", "models.0.dataset.npz": ".npz"}
BAD_PATHS = {"nul_byte": '"bad\\0name{}"', "unknown_user": "~fuzz-no-such-user/x{}",
             "name_too_long": "x" * 300 + "{}"}


def path_cases() -> list[Case]:
    """Paths the system refuses (a NUL byte, an unknown ~user, too long a name); a python_path not there."""
    cases = [Case(f"{key}={name}", lambda _p, t=render(context(key), raw.format(suffix), key_path(key)): t,
                  ((shown(key),),)) for key, suffix in PATHS.items() for name, raw in BAD_PATHS.items()]
    missing = render(context("models.0.python_path"), "no/such/dir", key_path("models.0.python_path.0"))
    return cases + [Case("models.0.python_path.0=missing_dir", lambda _p: missing,
                         (("models[0].python_path",), ("no/such/dir",)))]


def after_line_1(opening: str) -> str:
    """`opening` on line 2, then eight comment lines and the rest: a parser notices only lines later."""
    lines = render().splitlines()
    return "\n".join([lines[0], opening, *(f"# line {i}" for i in range(3, 11)), *lines[1:]]) + "\n"


TAIL = "dataset:" + render().split("dataset:", 1)[1]
SYNTAX = {  # name -> (matrix text, what the message names besides the file)
    "unclosed_flow_mapping": (after_line_1("  - {name: tiny, framework: onnx"), ("line 2", ":2:")),
    "tab_indentation": ("models:\n\t- {name: tiny}\n", (":2:", "line 2")),
    "mapping_in_scalar": ("models: a: b\n", (":1:", "line 1")),
    "two_documents": (render() + "---\n" + render(), ()), "empty_file": ("", ()),
    "comments_only": ("# x\n", ()), "document_marker_only": ("---\n", ()), "null_document": ("null\n", ()),
    "top_level_list": ("- models\n", ()), "top_level_int": ("42\n", ()),
    "recursive_alias": ("models: &m\n  - {name: tiny, framework: onnx, file: tiny.onnx, x: *m}\n" + TAIL, ()),
    "recursive_alias_in_mapping": ("axes: &a {strategy: [*a]}\n" + render().split("axes:")[0], ()),
    "deep_flow_nesting": ("models: " + "[" * 20000 + "]" * 20000 + "\n", ()),
    "deep_block_nesting": ("".join(" " * i + "a:\n" for i in range(2000)) + " " * 2000 + "a: 1\n", ()),
    "merge_key": ("models:\n  - &m {name: tiny, framework: onnx, file: tiny.onnx}\n"
                  "  - {<<: *m, name: tiny2}\n" + TAIL, ("models[1]",)),
    "binary_tag": (render().replace("name: tiny", "name: !!binary aGVsbG8="), ("models[0].name",)),
    "set_tag": (render().replace("strategy:\n  - none", "strategy: !!set {none}"), ("axes.strategy",)),
    "custom_tag": ("include: !include other.yaml\n" + render(), ("include",)),
}
def nested(levels: int, value: str) -> str:
    """`deep:` holding `levels` nested block mappings, the last one's `a:` holding `value`."""
    return "deep:\n" + "".join(" " * i + " a:\n" for i in range(levels - 1)) + " " * levels + f"a: {value}\n"


LINES = len(render().splitlines())
ONE_MODEL = "- name: tiny\n  framework: onnx\n  file: tiny.onnx\n"
LOCATED = {  # name -> (matrix text, the line its message must start at, what else it names)
    "unclosed_quote": (after_line_1('  - name: "tiny'), 2, "column 11"),
    "unclosed_quote_at_the_end": (render() + "description: 'never closed\n", LINES + 1, "quoted scalar"),
    "deep_block_nesting": (render() + nested(60, "1"), LINES + 51, "limit 50"),
    "deep_through_an_alias": ("anchor: &d " + "[" * 30 + "]" * 30 + "\n" + render() + nested(25, "*d"),
                              LINES + 27, "limit 50"),
    "alias_in_a_list": ("description: &p int4\n" + render().replace("  - fp32\n", "  - fp32\n  - *p\n"), 19,
                        "axes.precision[1]: 'int4' is not allowed"),
    "alias_of_a_model": (render().replace(ONE_MODEL, "- &m {name: tiny, framework: onnx, file: tiny.onnx}\n"
                                                     "- *m\n"), 3, "line 2"),
    "recursive_alias_on_its_own_line": ("axes: &a\n  strategy:\n  - *a\n" + render().split("axes:")[0], 3,
                                        "recursive alias"),
}
UNFIT = {  # name -> (the npz's x per sample, the model file): data the model's input cannot take
    "npz_rank_too_low": ((16,), "tiny.onnx"), "npz_rank_too_high": ((2, 3, 16, 16), "tiny.onnx"),
    "onnx_input_mismatch": ((3, 8, 8), "bad.onnx"),
}


def unfit(project: Path, name: str) -> str:
    """`name`.npz with x of the case's shape, and its model file (a copy of tiny.onnx): the matrix of both."""
    shape, model = UNFIT[name]
    np.savez(project / f"{name}.npz", x=np.zeros((48, *shape), np.float32), y=np.zeros((48, 2), np.float32))
    (project / model).write_bytes(onnx_model())
    return render(((("dataset", "npz"), f"{name}.npz"), (("models", 0, "file"), model)))


TYPES = {  # name -> (key path, raw YAML value, what the message names)
    "models_mapping": ("models", "{}", "models"), "models_string": ("models", "tiny", "models"),
    "models_item_int": ("models", "[5]", "models[0]"), "models_item_list": ("models", "[[]]", "models[0]"),
    "axes_list": ("axes", "[none]", "axes"), "settings_int": ("settings", "5", "settings"),
    "dataset_string": ("dataset", "data.npz", "dataset"),
    "axis_string": ("axes.strategy", "none", "axes.strategy"),
    "axis_empty": ("axes.strategy", "[]", "axes.strategy"),
    "axis_twice": ("axes.precision", "[fp32, fp32]", "axes.precision"),
    "precision_typo": ("axes.precision", "[int4]", "axes.precision"),
    "backend_typo": ("axes.backend", "[onnxruntme]", "axes.backend"),
    "name_int": ("models.0.name", "5", "models[0].name"),
    "name_emoji": ("models.0.name", "'t🚀'", "models[0].name"),
    "framework_case": ("models.0.framework", "ONNX", "models[0].framework"),
    "file_int": ("models.0.file", "5", "models[0].file"), "version_2": ("version", "2", "version"),
    "include_mapping": ("include", "{backend: onnxruntime}", "include"),
    "exclude_empty_entry": ("exclude", "[{}]", "exclude[0]"),
    "exclude_unknown_model": ("exclude", "[{model: tinny}]", "exclude[0].model"),
    "split_sum": ("dataset.split", "{train: 0.7, calibration: 0.2, test: 0.2}", "dataset.split"),
    "mean_without_std": ("dataset.preprocess", "{mean: [0.5]}", "dataset.preprocess"),
    "crop_bottom_above_top": ("dataset.preprocess", "{crop: {top: 10, bottom: 5}}", "preprocess.crop"),
    "resize_zero": ("dataset.preprocess", "{resize: [0, 16]}", "dataset.preprocess.resize"),
    "resize_three_values": ("dataset.preprocess", "{resize: [16, 16, 3]}", "dataset.preprocess.resize"),
    "typo_top_level": ("modles", "[]", "modles"),
    "typo_settings": ("settings.thread", "1", "settings.thread"),
    "typo_model_key": ("models.0.framwork", "onnx", "models[0]"),
    "typo_dataset_key": ("dataset.nzp", "x", "dataset.nzp"),
    "task_typo": ("dataset.task", "classify", "dataset.task"),
    "model_task_typo": ("models.0.task", "regresion", "models[0].task"),
    "model_dataset_two_kinds": ("models.0.dataset", "{npz: data.npz, synthetic: {samples: 8}}",
                                "models[0].dataset"),
    "images_missing": ("dataset", "{images: no/such/dir}", "dataset.images"),
    "synthetic_with_labels": ("dataset", "{synthetic: {samples: 8}, labels: {columns: [y]}}",
                              "dataset.labels"),
    "input_dtype_typo": ("models.0.inputs", "[{name: X, shape: [3, 16, 16], dtype: flaot32}]",
                         "models[0].inputs[0].dtype"),
    "input_names_twice": ("models.0.inputs", "[{name: X, shape: [3]}, {name: X, shape: [3]}]",
                          "models[0].inputs[1].name"),
    "input_shape_string": ("models.0.inputs", "[{name: X, shape: '3x16x16'}]", "models[0].inputs[0].shape"),
    "input_range_reversed": ("models.0.inputs", "[{name: X, shape: [3], range: [1, 0]}]",
                             "models[0].inputs[0].range"),
    "backend_options_typo": ("backend_options", "{onnxruntme: {}}", "backend_options.onnxruntme"),
    "backend_options_list": ("backend_options", "[onnxruntime]", "backend_options"),
    "metrics_unknown": ("metrics", "[no_such_metric]", "metrics[0]"),
}
STRATEGIES = {  # name -> (the strategies section, what the message names)
    "kind_typo": ("{s: {kindd: ptq_static}}", ("strategies.s",), ("did you mean 'kind'",)),
    "steps_typo": ("{s: {stepss: [prune, ptq_static]}}", ("strategies.s",), ("did you mean 'steps'",)),
    "option_typo": ("{s: {kind: ptq_static, calibraton_samples: 10}}", ("'calibration_samples'?",)),
    "kind_and_steps": ("{s: {kind: prune, steps: [prune, ptq_static]}}", ("strategies.s",)),
    "step_unknown": ("{s: {steps: [prune, ptq_dynmic]}}", ("strategies.s.steps",), ("ptq_dynmic",)),
    "step_itself": ("{s: {steps: [s, ptq_static]}}", ("strategies.s.steps",)),
    "conversion_first": ("{s: {steps: [ptq_static, prune]}}", ("strategies.s.steps",)),
    "kind_renamed": ("{ptq_static: {kind: ptq_dynamic}}", ("strategies.ptq_static",)),
    "option_of_other_kind": ("{s: {kind: ptq_dynamic, io: int8}}", ("strategies.s",)),
    "name_with_space": ("{'a b': {kind: prune}}", ("strategies",)),
}
TAGS = {  # YAML that constructs objects; MARKER is the file its payload would write
    "python_apply": "x: !!python/object/apply:os.system ['touch MARKER']\n",
    "python_exec_in_list": "y: [1, !!python/object/apply:builtins.exec [\"open('MARKER', 'w')\"]]\n",
    "python_new": "z: !!python/object/new:subprocess.Popen {args: [[touch, MARKER]]}\n",
    "python_name": "w: !!python/name:os.system\n", "python_module": "v: !!python/module:os\n",
    "python_tag_as_key": "? !!python/object/apply:os.system ['touch MARKER']\n: 1\n",
}
ENCODINGS = {"non_utf8_byte": render().encode() + b"description: caf\xe9\n",
             "utf16": render().encode("utf-16"), "nul_byte": render().encode() + b"name: a\0b\n",
             "control_char": render().encode() + b"name: a\x07b\n"}


def tagged(text: str) -> Callable[[Path], str]:
    return lambda project: text.replace("MARKER", str(markers(project) / "yaml")) + render()


def text_cases() -> list[Case]:
    """Syntax errors, wrong types, typos, impossible combinations, encodings and python tags."""
    cases = [Case(f"syntax:{name}", lambda _p, t=text: t, (names,) if names else ())
             for name, (text, names) in SYNTAX.items()]
    cases += [Case(f"unfit:{name}", lambda p, n=name: unfit(p, n),
                   ((f"{name}.npz",), (model,), ("models[0]",))) for name, (_shape, model) in UNFIT.items()]
    cases += [Case(f"located:{name}", lambda _p, t=text: t, ((rf"re:fuzz\.yaml:{line}: ",), (names,)))
              for name, (text, line, names) in LOCATED.items()]
    for name, (dotted, raw, names) in TYPES.items():
        top_level = dotted.split(".")[0] not in BASE
        text = render() + f"{dotted}: {raw}\n" if top_level else render((), raw, key_path(dotted))
        cases.append(Case(f"type:{name}", lambda _p, t=text: t, ((names,),)))
    for name, (section, *names) in STRATEGIES.items():
        text = render(((("axes", "strategy"), ["none"]),), section, ("strategies",))
        cases.append(Case(f"strategy:{name}", lambda _p, t=text: t, tuple(names)))
    cases += [Case(f"tag:{name}", tagged(text), (), "yaml") for name, text in TAGS.items()]
    return cases + [Case(f"bytes:{name}", lambda _p, b=data: b) for name, data in ENCODINGS.items()]
