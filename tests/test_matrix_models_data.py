"""The matrix keys of any model a user brings: datasets (builtin driving_bends, image folders, synthetic),
tasks, a model's own inputs, task and dataset, backend_options and metrics; each accepted, each mistake
located."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from bench_matrix.data import fingerprint
from bench_matrix.errors import MatrixError
from bench_matrix.matrix.load import load_matrix
from bench_matrix.tensors import TensorSpec
from conftest import TESTS, cli
from fuzz_cases import onnx_model

AXES = "axes: {strategy: [none], precision: [fp32], target: [cpu]}\n"
ONNX = "  - {name: m, framework: onnx, file: m.onnx}\n"
ONNX_BLOCK = "  - name: m\n    framework: onnx\n    file: m.onnx\n"  # a model mistake's keys start at line 5
FACTORY = (f"  - {{name: f, framework: pytorch, factory: 'tiny_models:tiny', weights: w.pt, "
           f"python_path: ['{TESTS}']}}\n")
FACTORY_BLOCK = FACTORY.replace("  - {", "  - ").replace("}\n", "\n").replace(", ", "\n    ")


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """m.onnx, w.pt (not read at load time), data.npz, and an image folder with two class subfolders."""
    (tmp_path / "m.onnx").write_bytes(onnx_model())
    (tmp_path / "w.pt").write_bytes(b"weights")
    (tmp_path / "data.npz").write_bytes(b"npz")
    for label in ("cat", "dog"):
        (tmp_path / "imgs" / label).mkdir(parents=True)
    return tmp_path


def write(project: Path, text: str) -> Path:
    path = project / "m.yaml"
    path.write_text(text)
    return path


def matrix(models: str, dataset: str, extra: str = "") -> str:
    return "models:\n" + models + f"dataset: {dataset}\n" + AXES + extra


def problems(project: Path, text: str) -> list[str]:
    with pytest.raises(MatrixError) as info:
        load_matrix(write(project, text))
    return info.value.problems


def test_image_folders_with_torchvision_preprocessing(project):
    pre = ("{resize_shorter: 256, center_crop: [224, 224], mean: [0.485, 0.456, 0.406], "
           "std: [0.229, 0.224, 0.225]}")
    loaded = load_matrix(write(project, matrix(ONNX, f"{{images: [imgs], preprocess: {pre}}}")))
    data = loaded.dataset
    assert (data.kind, data.task, data.paths) == ("images", "classification", (project / "imgs",))
    assert data.preprocess.resize_shorter == 256 and data.preprocess.center_crop == (224, 224)
    assert data.labels.offset is None and loaded.task_of(loaded.models[0]) == "classification"


@pytest.mark.parametrize("dataset, task", [("{builtin: driving}", "regression"),
                                           ("{builtin: driving_bends}", "classification"),
                                           ("{builtin: driving_bends, task: none}", "none"),
                                           ("{npz: data.npz}", "regression"),
                                           ("{npz: data.npz, task: classification}", "classification"),
                                           ("{synthetic: {samples: 64}}", "none")])
def test_each_dataset_has_its_default_task(project, dataset, task):
    data = load_matrix(write(project, matrix(ONNX, dataset))).dataset
    assert data.task == task and data.circuits == 20  # the documented default, whatever the kind


def test_a_scale_given_is_told_from_the_default_and_keys_the_cache(project):
    default = load_matrix(write(project, matrix(ONNX, "{npz: data.npz}"))).dataset
    text = matrix(ONNX, "{npz: data.npz, preprocess: {scale: 0.00392156862745098}}")
    given = load_matrix(write(project, text)).dataset
    assert default.preprocess.scale is None and given.preprocess.scale == pytest.approx(1 / 255)
    assert fingerprint(default) != fingerprint(given)  # 1/255 given is no default: cached apart


def test_synthetic_inputs_of_declared_shapes_dtypes_and_ranges(project):
    inputs = ("    inputs:\n      - {name: input_ids, shape: [null], dtype: int64, range: [0, 30000]}\n"
              "      - {name: attention_mask, shape: [128], dtype: int64}\n")
    loaded = load_matrix(write(project, matrix(FACTORY_BLOCK + inputs, "{synthetic: {samples: 64}}")))
    assert (loaded.dataset.kind, loaded.dataset.samples) == ("synthetic", 64)
    assert loaded.models[0].inputs == (TensorSpec("input_ids", (None,), "int64", (0, 30000)),
                                       TensorSpec("attention_mask", (128,), "int64", None))


def test_a_model_has_its_own_dataset_and_task(project):
    own = ("    dataset: {npz: data.npz, task: classification}\n"
           "  - {name: n, framework: onnx, file: m.onnx, task: none}\n")
    loaded = load_matrix(write(project, matrix(ONNX_BLOCK + own, "{builtin: driving}")))
    first, second = loaded.models
    assert first.dataset.paths == (project / "data.npz",)
    assert loaded.dataset_of(first).task == "classification"
    assert loaded.task_of(first) == "classification" and second.dataset is None
    assert loaded.dataset_of(second) is loaded.dataset and loaded.task_of(second) == "none"


def test_backend_options_of_an_installed_backend(project):
    text = matrix(ONNX, "{npz: data.npz}", "backend_options: {onnxruntime: {}}\n")
    loaded = load_matrix(write(project, text))
    assert loaded.backend_options == {"onnxruntime": {}}


def test_metrics_name_installed_metric_plugins(project, monkeypatch):
    dist = project / "site" / "my_metrics-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-metrics\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bench_matrix.metrics]\nsteer_error = my_metrics:SteerError\n")
    monkeypatch.syspath_prepend(str(project / "site"))
    load_matrix(write(project, matrix(ONNX, "{npz: data.npz}", "metrics: [steer_error]\n")))
    (problem,) = problems(project, matrix(ONNX, "{npz: data.npz}", "metrics: [steer_eror]\n"))
    assert (":5: metrics[0]: no metric plugin 'steer_eror' is installed; installed: steer_error; "
            "did you mean 'steer_error'?") in problem


DATASET_MISTAKES = [
    ("{images: imgs, task: regression}",
     "dataset.task: task 'regression' does not fit image folders, whose labels are their class subfolders; "
     "allowed: classification, none"),
    ("{builtin: driving, task: classification}",
     "dataset.task: task 'classification' does not fit the builtin driving data, whose labels are [v, w] "
     "speeds; allowed: regression"),
    ("{synthetic: {samples: 8}, task: regression}",
     "does not fit synthetic data, which has no labels; allowed: none"),
    ("{builtin: driving_bend}",
     "dataset.builtin: 'driving_bend' is not allowed; allowed: driving, driving_bends; did you mean "
     "'driving_bends'?"),
    ("{npz: data.npz, task: classify}", "dataset.task: 'classify' is not allowed; allowed: regression, "
                                        "classification, none; did you mean 'classification'?"),
    ("{synthetic: {samples: 0}}", "dataset.synthetic.samples: must be >= 1, got 0"),
    ("{synthetic: {samples: 2000000}}", "dataset.synthetic.samples: must be <= 1000000, got 2000000"),
    ("{synthetic: {}}", "dataset.synthetic: missing required key 'samples'"),
    ("{synthetic: {samples: 8}, circuits: 5}",
     "dataset.circuits: 'circuits' only applies to the builtin dataset"),
    ("{synthetic: {samples: 8}, preprocess: {scale: 1}}",
     "dataset.preprocess: 'preprocess' does not apply to synthetic data"),
    ("{images: imgs, labels: {columns: [y]}}", "dataset.labels: 'labels' does not apply to image folders"),
    ("{builtin: driving_bends, labels: {scale: [2]}}",
     "'labels' does not apply to the builtin driving_bends"),
    ("{images: [imgs, nothing]}", "dataset.images[1]: image folder not found: "),
    ("{images: m.onnx}", "m.onnx is a file, not a directory"),
    ("{npz: data.npz, images: imgs}", "dataset: give exactly one of 'builtin', 'npz', 'folder', 'images' or "
                                      "'synthetic'"),
    ("{images: imgs, preprocess: {resize: [64, 64], resize_shorter: 64}}",
     "dataset.preprocess.resize_shorter: give 'resize' ([height, width]) or 'resize_shorter'"),
    ("{images: imgs, preprocess: {resize: [64, 64], center_crop: [80, 32]}}",
     "dataset.preprocess.center_crop: [80, 32] does not fit in the resized [64, 64] image"),
    ("{images: imgs, preprocess: {resize_shorter: 64, center_crop: [80, 72]}}",
     "dataset.preprocess.center_crop: [80, 72] does not fit in an image whose shorter side is 64"),
    ("{images: imgs, preprocess: {center_crop: [224]}}",
     "dataset.preprocess.center_crop: [224] is too short"),
    ("{images: imgs, preprocess: {resize_shorter: 0}}",
     "dataset.preprocess.resize_shorter: must be >= 1, got 0"),
]


@pytest.mark.parametrize("dataset, message", DATASET_MISTAKES, ids=[m[0] for m in DATASET_MISTAKES])
def test_dataset_mistakes_are_located(project, dataset, message):
    (problem,) = problems(project, matrix(ONNX, dataset))
    assert problem.startswith(f"{project / 'm.yaml'}:3: ") and message in problem, problem


def inputs(*entries: str) -> str:
    return "    inputs:\n" + "".join(f"      - {e}\n" for e in entries)


MODEL_MISTAKES = [
    (inputs("{name: x, shape: [3], dtype: float}"), "{npz: data.npz}",
     ":6: models[0].inputs[0].dtype: 'float' is not allowed; allowed: float32, float16, float64, bfloat16, "
     "int64"),
    (inputs("{name: x, shape: [0]}"), "{npz: data.npz}",
     ":6: models[0].inputs[0].shape[0]: each axis is a whole number from 1 to 1000000, or null (any length)"),
    (inputs("{name: x, shape: [3], dtyp: int64}"), "{npz: data.npz}",
     ":6: models[0].inputs[0].dtyp: unknown key 'dtyp'; allowed: dtype, name, range, shape; did you mean "
     "'dtype'?"),
    (inputs("{name: x, shape: [3]}", "{name: x, shape: [4]}"), "{npz: data.npz}",
     ":7: models[0].inputs[1].name: input name 'x' is used twice (also inputs[0]); input names must be "
     "unique"),
    (inputs("{name: x, shape: [3], range: [5, 1]}"), "{npz: data.npz}",
     ":6: models[0].inputs[0].range: low (5) must be less than high (1)"),
    (inputs("{name: x, shape: [3], dtype: int8, range: [0, 1000]}"), "{npz: data.npz}",
     ":6: models[0].inputs[0].range: [0, 1000) does not fit int8 (-128 to 127)"),
    (inputs("{name: x, shape: [3], dtype: int64, range: [0.5, 3]}"), "{npz: data.npz}",
     "models[0].inputs[0].range: an int64 input's range is whole numbers"),
    (inputs("{name: x, shape: [100000, 100000]}"), "{npz: data.npz}",
     "models[0].inputs[0].shape: 10000000000 values per sample (free axes counted as 8); limit 67108864"),
    (inputs("{name: a, shape: [3, 8, 8]}", "{name: b, shape: [4]}"), "{images: imgs}",
     ":5: models[0].inputs: image folders feed one input, but the model declares 2 (a, b)"),
    ("    task: regression\n", "{builtin: driving_bends}",
     ":5: models[0].task: task 'regression' does not fit the builtin driving_bends data"),
    ("    dataset: {npz: data.npz, splt: {test: 0.5}}\n", "{builtin: driving}",
     ":5: models[0].dataset.splt: unknown key 'splt'; allowed: builtin, "),
    ("    dataset: {npz: missing.npz}\n", "{builtin: driving}",
     ":5: models[0].dataset.npz: dataset file not found: "),
]


@pytest.mark.parametrize("extra, dataset, message", MODEL_MISTAKES,
                         ids=[m[2].split(": ")[0].lstrip(":0123456789") for m in MODEL_MISTAKES])
def test_model_mistakes_are_located(project, extra, dataset, message):
    (problem,) = problems(project, matrix(ONNX_BLOCK + extra, dataset))
    assert problem.startswith(str(project / "m.yaml")) and message in problem, problem


@pytest.mark.parametrize("model, message", [
    ("  - {name: b, framework: pytorch, builtin: pilotnet}\n",
     ":2: models[0].builtin: a built-in model is trained on its dataset's labels, and synthetic data has "
     "none"),
    (FACTORY, ":2: models[0]: a factory model on synthetic data must declare 'inputs'"),
    ("  - {name: b, framework: pytorch, builtin: pilotnet, inputs: [{name: x, shape: [3]}]}\n",
     "models[0].inputs: 'inputs' is for file and factory models"),
])
def test_models_that_synthetic_data_cannot_serve(project, model, message):
    found = problems(project, matrix(model, "{synthetic: {samples: 8}}"))
    assert any(message in p for p in found), found


def test_a_mistake_in_a_new_key_exits_2_through_the_cli(project):
    write(project, matrix(ONNX, "{images: imgs, task: regression}"))
    paths = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    done = cli(project, "plan", "m.yaml", env={"PYTHONPATH": paths})
    assert done.returncode == 2, done.stdout + done.stderr
    assert "m.yaml:3: dataset.task: task 'regression' does not fit image folders" in done.stderr
