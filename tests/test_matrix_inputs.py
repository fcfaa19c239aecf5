"""Broken and hostile matrix files, paths, settings and options: located messages, exit 2, no hang."""

from __future__ import annotations

import os
import re
import socket
import sqlite3
import time
from contextlib import closing
from pathlib import Path

import pytest

from bench_matrix.cli import main
from bench_matrix.errors import MatrixError, UserError
from bench_matrix.matrix.load import load_matrix
from bench_matrix.matrix.schema import SCHEMA
from bench_matrix.store import ResultStore
from bench_matrix.workspace import file_sha256
from test_matrix import BASE

DOCS = Path(__file__).parents[1] / "docs" / "matrix.md"


def problems(path: Path) -> list[str]:
    with pytest.raises(MatrixError) as info:
        load_matrix(path)
    return info.value.problems


def matrix(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "m.yaml"
    path.write_text(text)
    return path


def only_problem(tmp_path: Path, text: str) -> str:
    (problem,) = problems(matrix(tmp_path, text))
    return problem


def cli_error(capsys: pytest.CaptureFixture, *argv: str) -> str:
    """Run the CLI in-process; it must exit 2 with one error and no traceback. Returns stderr."""
    assert main(list(argv)) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "Traceback" not in err
    return err


# --- YAML -------------------------------------------------------------------------------------------------


def test_recursive_alias_is_refused(tmp_path):
    problem = only_problem(tmp_path, "a: &a [*a]\n")
    assert problem.startswith(f"{tmp_path / 'm.yaml'}:1: a[0]: a recursive alias")


def test_alias_bomb_stops_at_the_value_limit(tmp_path):
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 10)]  # 9**10 values expanded
    begin = time.monotonic()
    problem = only_problem(tmp_path, "\n".join(lines) + "\n")
    assert time.monotonic() - begin < 10  # stopped early (0.1 s here): 9**10 values would not fit in memory
    assert re.search(r"m\.yaml:6: a5: aliases expand this to more than 100000 values: .*limit 100000$",
                     problem)


FLOW_NESTING = "a: " + "[" * 10_000 + "]" * 10_000 + "\n"
BLOCK_NESTING = "".join("  " * i + f"k{i}:\n" for i in range(60)) + "  " * 60 + "x: 1\n"


@pytest.mark.parametrize("text, line", [(FLOW_NESTING, 1), (BLOCK_NESTING, 51)])
def test_deep_nesting_stops_at_the_depth_limit(tmp_path, text, line):
    assert only_problem(tmp_path, text) == (f"{tmp_path / 'm.yaml'}:{line}: nesting too deep: more than 50 "
                                            f"levels of mappings and lists; limit 50")


def test_aliases_cannot_nest_past_the_depth_limit(tmp_path):
    deep = "[" * 30 + "x" + "]" * 30
    problem = only_problem(tmp_path, f"a: &a {deep}\nb: {'[' * 30}*a{']' * 30}\n")
    assert problem.startswith(f"{tmp_path / 'm.yaml'}:2: b: aliases expand this to more than 50 levels")


@pytest.mark.parametrize("text, expected", [
    ('models:\n  - name: "abc\n    framework: x\n',
     ":2: not valid YAML: a quoted scalar that starts here (column 11) is never closed: the file ends first "
     "(line 4)"),
    ("models: [a,\n  b\n",
     ":1: not valid YAML: a flow sequence that starts here (column 9) is never closed: the file ends first "
     "(line 3)"),
    ("a: 1\nb: \x00\n", ":2: not valid YAML: the character #x0000 is not allowed"),
])
def test_syntax_errors_keep_where_the_construct_started(tmp_path, text, expected):
    assert expected in only_problem(tmp_path, text)


def test_a_lone_surrogate_is_not_text(tmp_path):
    problem = only_problem(tmp_path, 'models: [{name: "a\\ud800"}]\n')
    assert problem.startswith(f"{tmp_path / 'm.yaml'}:1: models[0].name: 'a\\ud800' holds '\\ud800', which "
                              f"is not a character")


def test_a_number_too_long_to_read(tmp_path):
    problem = only_problem(tmp_path, "a: 1" + "0" * 5000 + "\n")
    where = f"{tmp_path / 'm.yaml'}:1"
    assert problem == f"{where}: a: a number of 5001 characters is too long to read; limit 4300 digits"


def test_unreadable_matrix_files(tmp_path, capsys):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("name: ok\ndescription: caf\xe9\n".encode("latin-1"))
    assert f"{bad}:2: the file is not UTF-8 text (byte 0xe9 at column 17); save it as UTF-8" in cli_error(
        capsys, "plan", str(bad))
    pipe = tmp_path / "pipe.yaml"
    os.mkfifo(pipe)
    assert f"{pipe}: is a named pipe, not a regular file" in cli_error(capsys, "plan", str(pipe))
    folder = cli_error(capsys, "plan", str(tmp_path))  # as `run`: a folder may be a SavedModel
    assert f"{tmp_path}: is a folder without saved_model.pb; expected a model file" in folder
    assert "or a matrix .yaml" in folder
    assert "/dev/zero: is a character device" in cli_error(capsys, "run", "/dev/zero")
    (tmp_path / "empty.yaml").write_text("")
    assert "empty.yaml: the file is empty" in cli_error(capsys, "plan", str(tmp_path / "empty.yaml"))
    (tmp_path / "huge.yaml").write_text("# padding\n" * 200_000)
    assert "limit 1048576 bytes" in cli_error(capsys, "plan", str(tmp_path / "huge.yaml"))


# --- paths ------------------------------------------------------------------------------------------------


def with_models(*entries: str, dataset: str = "builtin: driving") -> str:
    """A matrix whose models[1], models[2], ... (lines 3, 4, ...) are `entries`."""
    lines = ["models:", "  - {name: a, framework: pytorch, builtin: pilotnet}",
             *[f"  - {e}" for e in entries], f"dataset: {{{dataset}}}",
             "axes: {strategy: [none], precision: [fp32], target: [cpu]}"]
    return "\n".join(lines) + "\n"


def test_paths_that_cannot_name_a_file(tmp_path):
    text = with_models('{name: b, framework: onnx, file: "m\\0.onnx"}',
                       "{name: c, framework: onnx, file: '~no_such_user_xyz/m.onnx'}",
                       f"{{name: d, framework: onnx, file: '{'d/' * 2100}m.onnx'}}")
    found = problems(matrix(tmp_path, text))
    assert any(":3: models[1].file: the path 'm\\x00.onnx' contains a NUL byte" in p for p in found)
    assert any(":4: models[2].file: cannot expand '~no_such_user_xyz'" in p and "no such user" in p
               for p in found)
    assert any(":5: models[3].file: the path is longer than 4096 bytes" in p for p in found)


def test_special_files_are_refused_without_being_opened(tmp_path):
    os.mkfifo(tmp_path / "pipe.pt")
    os.mkfifo(tmp_path / "data.npz")
    listener = socket.socket(socket.AF_UNIX)
    listener.bind(str(tmp_path / "sock.onnx"))
    try:
        found = problems(matrix(tmp_path, with_models(
            "{name: b, framework: pytorch, file: pipe.pt}", "{name: c, framework: onnx, file: sock.onnx}",
            "{name: d, framework: onnx, file: /dev/null}",
            "{name: e, framework: pytorch, factory: 'tiny_models:tiny', weights: pipe.pt}",
            dataset="npz: data.npz")))
    finally:
        listener.close()
    assert any("models[1].file: '" in p and "pipe.pt' is a named pipe, not a model file" in p for p in found)
    assert any("models[2].file: '" in p and "sock.onnx' is a socket, not a model file" in p for p in found)
    assert any("models[3].file: '/dev/null' is a character device, not a model file" in p for p in found)
    assert any("models[4].weights: " in p and "pipe.pt is a named pipe, not a weights file" in p
               for p in found)
    assert any("dataset.npz: " in p and "data.npz is a named pipe, not a dataset file" in p for p in found)
    link = tmp_path / "zero.onnx"
    link.symlink_to("/dev/zero")
    problem = only_problem(tmp_path, with_models(f"{{name: b, framework: onnx, file: '{link}'}}"))
    assert f"models[1].file: '{link}' is a character device, not a model file" in problem  # the user's name
    with pytest.raises(UserError, match="is a named pipe, not a regular file"):
        file_sha256(tmp_path / "pipe.pt")  # the parent's hashing never blocks on a pipe either


def test_saved_model_directory_must_hold_regular_files(tmp_path):
    saved = tmp_path / "sm"
    (saved / "variables").mkdir(parents=True)
    (saved / "saved_model.pb").write_bytes(b"graph")
    os.mkfifo(saved / "variables" / "variables.data-00000-of-00001")
    problem = only_problem(tmp_path, with_models("{name: b, framework: tensorflow, file: sm}"))
    assert "models[1].file: " in problem
    assert "variables.data-00000-of-00001 in the SavedModel is a named pipe" in problem


def test_python_path_entries_must_be_existing_folders(tmp_path):
    (tmp_path / "w.pt").write_bytes(b"weights")
    (tmp_path / "src").mkdir()
    found = problems(matrix(tmp_path, with_models("{name: b, framework: pytorch, factory: 'pkg.mod:build', "
                                                  "weights: w.pt, python_path: [src, nowhere, w.pt]}")))
    assert [p.split(": ", 1)[1] for p in found] == [
        f"models[1].python_path[1]: python_path folder not found: {tmp_path / 'nowhere'} (python_path lists "
        f"folders to import 'factory' from)",
        f"models[1].python_path[2]: {tmp_path / 'w.pt'} is a file, not a directory (python_path lists "
        f"folders to import 'factory' from)"]


@pytest.mark.parametrize("factory", ["pkg..mod:build", "pkg.mod", "pkg.mod:", ":build", "pkg.mod:build()"])
def test_factory_must_be_module_colon_function(tmp_path, factory):
    (tmp_path / "w.pt").write_bytes(b"weights")
    problem = only_problem(tmp_path, with_models(f"{{name: b, framework: pytorch, factory: '{factory}', "
                                                 f"weights: w.pt}}"))
    assert f":3: models[1].factory: write it as 'package.module:function' (got '{factory}')" in problem


def test_folder_dataset_checks(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "pipe").mkdir()
    os.mkfifo(tmp_path / "pipe" / "data.csv")
    text = BASE.replace("builtin: driving", "folder: [empty, file.txt, missing, pipe]")
    found = problems(matrix(tmp_path, text))
    assert found == [
        f"{tmp_path / 'm.yaml'}:6: dataset.folder[0]: {tmp_path / 'empty'} has no data.csv (expected header "
        f"image_name,v,w,...)",
        f"{tmp_path / 'm.yaml'}:6: dataset.folder[1]: {tmp_path / 'file.txt'} is a file, not a directory",
        f"{tmp_path / 'm.yaml'}:6: dataset.folder[2]: dataset folder not found: {tmp_path / 'missing'}",
        f"{tmp_path / 'm.yaml'}:6: dataset.folder[3]: {tmp_path / 'pipe' / 'data.csv'} is a named pipe, "
        f"not a data.csv file; give a regular file"]


# --- numbers ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("setting, message", [
    ("threads: 2.0", "settings.threads: expected integer, got float 2.0; write it without a decimal point"),
    ("batch_size: 1.0e+30", "settings.batch_size: expected integer, got float 1e+30"),
    ("min_rounds: true", "settings.min_rounds: expected integer, got bool True"),
    ("window_s: .nan", "settings.window_s: expected a finite number, got float nan"),
    ("timeout_s: .inf", "settings.timeout_s: expected a finite number, got float inf"),
    ("warmup_s: -.inf", "settings.warmup_s: expected a finite number, got float -inf"),
    ("timeout_s: 1.0e+30", "settings.timeout_s: must be <= 604800, got 1e+30"),
    ("warmup_iterations: 100000000", "settings.warmup_iterations: must be <= 1000000, got 100000000"),
    ("min_rounds: 1", "settings.min_rounds: must be >= 2, got 1"),
    ("ci_target: 0", "settings.ci_target: must be > 0, got 0"),
    ("seed: -1", "settings.seed: must be >= 0, got -1"),
    ("threads: true", "settings.threads: expected integer, got bool True"),
])
def test_settings_reject_what_cannot_be_meant(tmp_path, setting, message):
    problem = only_problem(tmp_path, BASE + f"settings: {{{setting}}}\n")
    assert problem.startswith(f"{tmp_path / 'm.yaml'}:11: {message}")


@pytest.mark.parametrize("dataset, message", [
    ("samples: 100.0", "dataset.samples: expected integer, got float 100.0"),
    ("samples: 1000000000", "dataset.samples: must be <= 200000"),
    ("circuits: 50\n  samples: 20", "dataset.circuits: 50 circuits for 20 samples"),
    ("preprocess: {resize: [66.0, 200]}", "dataset.preprocess.resize[0]: expected integer, got float 66.0"),
    ("preprocess: {resize: [100000, 200]}", "dataset.preprocess.resize[0]: must be <= 8192"),
    ("preprocess: {scale: .nan}", "dataset.preprocess.scale: expected a finite number, got float nan"),
    ("labels: {offset: [.inf]}", "dataset.labels.offset[0]: expected a finite number, got float inf"),
    ("preprocess: {crop: {top: 10, bottom: 5}}", "dataset.preprocess.crop.bottom: bottom (5) must be greater "
                                                 "than top (10): the bounds are slice bounds"),
    ("preprocess: {crop: {left: 7, right: 7}}",
     "dataset.preprocess.crop.right: right (7) must be greater than left (7)"),
])
def test_dataset_numbers_are_strict(tmp_path, dataset, message):
    text = BASE.replace("builtin: driving", f"builtin: driving\n  {dataset}")
    assert message in only_problem(tmp_path, text)


def test_strategy_and_training_numbers_are_strict(tmp_path):
    text = BASE.replace("builtin: pilotnet", "builtin: pilotnet\n    training: {epochs: 2.0, lr: .nan}") + (
        "strategies:\n  s: {kind: ptq_static, calibration_samples: 1.0e+30}\n"
        "  p: {kind: prune, epochs: 1.0e+9}\n")
    found = problems(matrix(tmp_path, text))
    assert [p.split(": ", 1)[1] for p in found] == [
        "models[0].training.epochs: expected integer, got float 2.0; write it without a decimal point",
        "models[0].training.lr: expected a finite number, got float nan (.nan and .inf are not allowed)",
        "strategies.p.epochs: must be <= 10000, got 1000000000.0",
        "strategies.s.calibration_samples: expected integer, got float 1e+30; write it without a decimal "
        "point"]


def test_values_at_the_limits_load(tmp_path):
    settings = ("settings: {timeout_s: 604800, threads: 1024, batch_size: 65536, seed: 2147483647, "
                "timing_budget_s: 86400, min_rounds: 1000, window_s: 60, memory_share: 1}\n")
    loaded = load_matrix(matrix(tmp_path, BASE + settings)).settings
    assert (loaded.timeout_s, loaded.threads, loaded.batch_size, loaded.min_rounds) == \
        (604800, 1024, 65536, 1000)
    assert (loaded.timing_budget_s, loaded.window_s, loaded.memory_share) == (86400, 60, 1)
    assert load_matrix(matrix(tmp_path, BASE)).dataset.circuits == 20  # the documented default


def test_every_settings_limit_is_in_the_schema_and_the_docs():
    section = DOCS.read_text().split("## 9. settings")[1].split("## 10.")[0]
    for key, rule in SCHEMA["properties"]["settings"]["properties"].items():
        assert "maximum" in rule, key
        row = next(line for line in section.splitlines() if line.startswith(f"| `{key}` |"))
        assert f" {rule['maximum']}" in row, (key, row)


# --- strategies -------------------------------------------------------------------------------------------


def test_strategy_kind_typo_names_the_key(tmp_path):
    text = BASE + "strategies:\n  mine: {knd: ptq_static, calibration_samples: 10}\n"
    assert only_problem(tmp_path, text) == (
        f"{tmp_path / 'm.yaml'}:12: strategies.mine.knd: unknown key 'knd'; allowed: description, kind, "
        f"steps (and the options of the kind); did you mean 'kind'?")


def test_strategy_with_kind_and_steps_gets_one_message(tmp_path):
    problem = only_problem(tmp_path, BASE + "strategies:\n  mine: {kind: ptq_static, steps: [prune, none]}\n")
    assert problem.endswith("strategies.mine: give either 'kind' (with its options) or 'steps' (a list of "
                            "strategy names), not both")


# --- command line -----------------------------------------------------------------------------------------


@pytest.fixture
def stores(tmp_path: Path) -> Path:
    """A folder of things that are not usable results stores."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "text.sqlite").write_text("model,p50\nnet,1.0\n" * 10)
    ResultStore(tmp_path / "newer.sqlite").close()
    (tmp_path / "truncated.sqlite").write_bytes((tmp_path / "newer.sqlite").read_bytes()[:1000])
    for name, sql in (("other.sqlite", "CREATE TABLE contacts (name TEXT)"),
                      ("newer.sqlite", "PRAGMA user_version = 9")):
        with closing(sqlite3.connect(tmp_path / name)) as db:
            db.execute(sql)
    return tmp_path


@pytest.mark.parametrize("command", ["report", "plan", "run"])
@pytest.mark.parametrize("name, message", [
    ("folder", "is a directory; give a file name such as"),
    ("text.sqlite", "not a bench-matrix results store: it is not an SQLite database"),
    ("truncated.sqlite", "not a bench-matrix results store (database disk image is malformed)"),
    ("other.sqlite", "an SQLite database, but not a bench-matrix results store (its tables: contacts)"),
    ("newer.sqlite", "written by a newer bench-matrix (results format 9; this one reads 2)"),
    ("missing/r.sqlite", "the folder"),
])
def test_results_option_problems(stores, capsys, command, name, message):
    path = stores / name
    matrix_args = [str(matrix(stores, BASE))] if command != "report" else []
    before = {p: p.read_bytes() for p in stores.glob("*.sqlite")}
    err = cli_error(capsys, "--workspace", str(stores / "ws"), command, *matrix_args, "--results", str(path))
    assert f"--results {path}: " in err
    if name == "missing/r.sqlite":
        assert ("does not exist" if command == "run" else "no such file") in err
    else:
        assert message in err
    assert {p: p.read_bytes() for p in stores.glob("*.sqlite")} == before  # nothing was written into them


def test_workspace_and_out_that_are_files(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("x")
    err = cli_error(capsys, "--workspace", str(notes), "plan", str(matrix(tmp_path, BASE)))
    assert f"--workspace {notes}: is a file; --workspace names a folder (for caches, logs and results)" in err
    err = cli_error(capsys, "--workspace", str(notes / "sub"), "backends")
    assert f"--workspace {notes / 'sub'}: cannot write there ({notes} is not a writable folder)" in err
    cli_error(capsys, "--workspace", str(tmp_path / "ws"), "run", str(matrix(tmp_path, "models: [\n")))
    assert not (tmp_path / "ws").exists()  # a command that stops early leaves no workspace behind
    ResultStore(tmp_path / "r.sqlite").close()
    err = cli_error(capsys, "report", "--results", str(tmp_path / "r.sqlite"), "--out", str(notes))
    assert f"--out {notes}: is a file; --out names a folder (the report's pages are written to)" in err
    err = cli_error(capsys, "report", "--results", str(tmp_path / "r.sqlite"), "--out", str(notes / "pages"))
    assert f"--out {notes / 'pages'}: cannot write there ({notes} is not a writable folder)" in err


def test_filter_option_without_a_value(tmp_path, capsys):
    err = cli_error(capsys, "--workspace", str(tmp_path / "ws"), "plan", str(matrix(tmp_path, BASE)),
                    "--model", ",")
    assert "--model ',': give at least one model" in err
