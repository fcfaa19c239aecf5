"""Fuzz test of every class of bad input (issue 11): generated broken and hostile matrix files and
command-line values (fuzz_cases.py), data files (fuzz_data_cases.py) and model files (fuzz_model_cases.py),
each asserted end to end:
the exit code, no traceback, a message naming the culprit, no advice to load a file unsafely, and no file
written by a payload."""

from __future__ import annotations

import json
import os
import pickle
import re
import subprocess
import sys
import traceback
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

import fuzz_cases as fc
import fuzz_data_cases as fd
import fuzz_model_cases as fm
from bench_matrix.cli import main
from bench_matrix.errors import UserError
from conftest import cli, popen_cli

UNSAFE_ADVICE = re.compile(r"weights_only\s*=\s*False|safe_mode\s*=\s*False|allow_pickle\s*=\s*True|"
                           r"allow_pickle=`|unsafely|safe_globals", re.IGNORECASE)
MATRIX = "fuzz.yaml"


@dataclass(frozen=True)
class Outcome:
    code: int | str | None
    text: str  # stdout and stderr, as the user sees them


def run_main(project: Path, args: list[str], capsys: pytest.CaptureFixture) -> Outcome:
    """`bench-matrix ARGS` in this process; an exception escaping main is what a user sees: a traceback."""
    if args[0] != "--workspace":
        args = ["--workspace", str(project / "ws"), *args]
    escaped = ""
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    except Exception:
        code, escaped = 1, traceback.format_exc()
    captured = capsys.readouterr()
    return Outcome(code, captured.out + captured.err + escaped)


def assert_no_traceback(text: str) -> None:
    assert "Traceback" not in text and 'File "' not in text, f"traceback shown:\n{text[-3000:]}"


def assert_told(text: str, culprit: fc.Culprit) -> None:
    """No traceback, one alternative of every culprit group named, no advice to load a file unsafely."""
    assert_no_traceback(text)
    for group in culprit:
        assert any(re.search(a[3:], text) if a.startswith("re:") else a in text for a in group), \
            f"message does not name any of {group}:\n{text[-3000:]}"
    assert not UNSAFE_ADVICE.search(text), f"message advises loading unsafely:\n{text[-3000:]}"


def assert_exit_2(outcome: Outcome, culprit: fc.Culprit) -> None:
    assert outcome.code == 2, f"exit {outcome.code}, expected 2:\n{outcome.text[-3000:]}"
    assert_told(outcome.text, culprit)


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny.onnx, tiny.pt (tiny_models:tiny), data.npz, and valid.yaml: the matrix every case changes once."""
    import torch
    from tiny_models import tiny

    root = fc.write_project(tmp_path_factory.mktemp("fuzz"))
    torch.save(tiny().state_dict(), root / "tiny.pt")
    (root / "valid.yaml").write_text(fc.render())
    return root


def test_the_base_matrix_is_valid_so_each_case_has_one_mistake(project, capsys):
    outcome = run_main(project, ["plan", str(project / "valid.yaml")], capsys)
    assert outcome.code == 0 and "1 will run" in outcome.text, outcome.text


def test_the_payloads_are_live(project):
    """Loaded unsafely, the pickle and YAML payloads write their marker: its absence later is evidence."""
    marker = fc.markers(project) / "live"
    pickle.loads(pickle.dumps(fc.Payload(marker)))
    assert marker.read_text() == "pwned"
    marker.unlink()
    yaml.unsafe_load(fc.TAGS["python_exec_in_list"].replace("MARKER", str(marker)))
    assert marker.exists()
    marker.unlink()


LISTED: dict[str, tuple] = {}  # entry-point group -> its entry points, as the registry first found them


@pytest.fixture
def backends_listed_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The registry lists the installed entry points once for the in-process commands below instead of once
    per backend per command (0.1 s of a plan's 0.13 s, 400 cases): nothing is installed or removed meanwhile,
    so each still imports and reads every backend as found, and judges its input against them."""
    import bench_matrix.registry as registry

    found = registry.entry_points

    def listed(*, group: str) -> tuple:
        if group not in LISTED:
            LISTED[group] = tuple(found(group=group))
        return LISTED[group]

    monkeypatch.setattr(registry, "entry_points", listed)


@pytest.mark.timeout(60)
@pytest.mark.usefixtures("backends_listed_once")
@pytest.mark.parametrize("case", fc.value_cases() + fc.path_cases() + fc.text_cases(), ids=lambda c: c.id)
def test_matrix_mistake_exits_2_naming_it(case: fc.Case, project: Path, capsys):
    marker = project / "markers" / "yaml"
    marker.unlink(missing_ok=True)
    content, path = case.build(project), project / MATRIX
    path.write_bytes(content) if isinstance(content, bytes) else path.write_text(content)
    assert_exit_2(run_main(project, ["plan", str(path)], capsys), ((MATRIX,),) + case.culprit)
    assert not marker.exists(), "a YAML tag ran its payload"


COMMANDS = {  # id -> (arguments: {m} is a valid matrix, {s} the scratch folder; what the message names)
    "report:results_is_a_directory": ("report --results {s}/dir.sqlite", ("dir.sqlite",)),
    "report:results_not_a_database": ("report --results {s}/notes.txt", ("notes.txt",)),
    "report:results_missing": ("report --results {s}/none/r.sqlite", ("r.sqlite",)),
    "report:out_is_a_file": ("report --results {s}/results.sqlite --format md --out {s}/a-file", ("a-file",)),
    "report:format_unknown": ("report --format xml", ("xml",)),
    "plan:results_not_a_database": ("plan {m} --results {s}/notes.txt", ("notes.txt",)),
    "plan:results_is_a_directory": ("plan {m} --results {s}/dir.sqlite", ("dir.sqlite",)),
    "run:results_is_a_directory": ("run {m} --results {s}/dir.sqlite", ("dir.sqlite",)),
    "run:results_not_a_database": ("run {m} --results {s}/notes.txt", ("notes.txt",)),
    "run:results_parent_is_a_file": ("run {m} --results {s}/a-file/r.sqlite", ("a-file",)),
    "plan:workspace_is_a_file": ("--workspace {s}/a-file plan {m}", ("a-file",)),
    "run:workspace_is_a_file": ("--workspace {s}/a-file run {m}", ("a-file",)),
    "backends:workspace_is_a_file": ("--workspace {s}/a-file backends", ("a-file",)),
    "run:backend_typo": ("run {m} --backend onnxruntme", ("onnxruntme",), ("did you mean 'onnxruntime'",)),
    "plan:precision_unknown": ("plan {m} --precision int4", ("int4",)),
    "run:target_unknown": ("run {m} --target gpu", ("gpu",)),
    "run:model_unknown": ("run {m} --model tinyy", ("tinyy",)),
    "plan:matrix_is_a_directory": ("plan {s}", ("scratch",)),
    "plan:matrix_missing": ("plan {s}/none.yaml", ("none.yaml",)),
    "run:no_matrix": ("run", ("matrix",)),
}


def scratch(project: Path) -> Path:
    """A directory, a text file, a plain file and a results store holding one record."""
    from bench_matrix.cell import Cell
    from bench_matrix.store import CellRecord, ResultStore

    folder = project / "scratch"
    if not folder.is_dir():
        (folder / "dir.sqlite").mkdir(parents=True)
        (folder / "notes.txt").write_text("not a database\n" * 100)
        (folder / "a-file").write_text("x")
        store = ResultStore(folder / "results.sqlite")
        run = store.begin_run("m.yaml", "fuzz", {})
        store.put(CellRecord(Cell("tiny", "onnx", "onnxruntime", "none", "fp32", "cpu"), "skipped", "fuzz",
                             run_id=run.id))
        store.close()
    return folder


@pytest.mark.timeout(120)
@pytest.mark.usefixtures("backends_listed_once")
@pytest.mark.parametrize("case", list(COMMANDS), ids=str)
def test_command_line_mistake_exits_2_naming_it(case: str, project: Path, capsys):
    command, *culprit = COMMANDS[case]
    args = command.format(m=project / "valid.yaml", s=scratch(project)).split()
    assert_exit_2(run_main(project, args, capsys), tuple(culprit))


UNBOUNDED = {  # id -> (command, key path, or None for the matrix itself; a file that never ends or explodes)
    "plan:matrix_fifo": ("plan", None, "pipe.yaml"), "plan:matrix_dev_zero": ("plan", None, "zero.yaml"),
    "plan:alias_bomb": ("plan", None, "laughs.yaml"),
    "plan:model_fifo": ("plan", "models.0.file", "pipe.onnx"),
    "run:model_fifo": ("run", "models.0.file", "pipe.onnx"),
    "plan:model_dev_zero": ("plan", "models.0.file", "zero.onnx"),
    "run:model_dev_zero": ("run", "models.0.file", "zero.onnx"),
    "plan:weights_fifo": ("plan", "models.0.weights", "pipe.pt"),
    "plan:npz_dev_zero": ("plan", "dataset.npz", "zero.npz"),
}


def unbounded_files(project: Path) -> Path:
    """FIFOs, links to /dev/zero, and a billion-laughs alias tree (10**9 nodes in 9 lines)."""
    folder = project / "unbounded"
    if not folder.is_dir():
        folder.mkdir()
        for name in ("zero.onnx", "zero.yaml", "zero.npz"):
            (folder / name).symlink_to("/dev/zero")
        for name in ("pipe.onnx", "pipe.yaml", "pipe.pt"):
            os.mkfifo(folder / name)
        laughs = "".join(f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]\n" for i in range(1, 9))
        (folder / "laughs.yaml").write_text(f"l0: &l0 [{', '.join(['lol'] * 10)}]\n" + laughs)
    return folder


@pytest.mark.parametrize("case", list(UNBOUNDED), ids=str)
def test_unbounded_input_exits_2_in_bounded_time_and_memory(case: str, project: Path):
    command, key, file = UNBOUNDED[case]
    path, culprit = unbounded_files(project) / file, ((file,),)
    if key:
        (project / MATRIX).write_text(fc.render(fc.context(key), str(path), fc.key_path(key)))
        path, culprit = project / MATRIX, culprit + ((fc.shown(key),),)
    limited = ["sh", "-c", 'ulimit -v 3145728 && exec "$@"', "sh"]  # 3 GiB (no preexec_fn: a thread runs)
    args = [*limited, sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), command,
            str(path)]
    try:
        done = subprocess.run(args, capture_output=True, text=True, timeout=20)
    except subprocess.TimeoutExpired:
        done = None
    assert done is not None, f"bench-matrix {command} ({file}) did not finish in 20 s"
    assert_exit_2(Outcome(done.returncode, done.stdout + done.stderr), culprit)


def prepare_data(project: Path, case: fc.Case) -> Outcome:
    """What `run` does with a dataset, in this process: validate the matrix, then read, check and split the
    data (the job a child does); a UserError there stops the run with exit 2, anything else is a traceback."""
    from bench_matrix.jobs import DatasetJob
    from bench_matrix.jobs.prepare import prepare_dataset
    from bench_matrix.matrix.load import load_matrix
    from bench_matrix.registry import available
    from bench_matrix.workspace import Workspace

    (project / "tiny.onnx").write_bytes(fc.onnx_model())
    (project / MATRIX).write_text(case.build(project))
    try:
        matrix = load_matrix(project / MATRIX, backends=list(available()))
        prepare_dataset(DatasetJob(workspace=Workspace(project / "ws"), dataset=matrix.dataset))
    except UserError as exc:
        return Outcome(exc.exit_code, f"error: dataset: {exc}")
    except Exception:
        return Outcome(1, traceback.format_exc())
    return Outcome(0, "the dataset was accepted")


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", fd.data_cases(), ids=lambda c: c.id)
def test_data_mistake_is_refused_naming_it(case: fc.Case, tmp_path: Path):
    assert_exit_2(prepare_data(tmp_path, case), case.culprit)
    assert not (case.marker and (tmp_path / "markers" / case.marker).exists()), "a payload in the data ran"


END_TO_END = ("npz:truncated", "npz:nan_labels", "npz:object_images", "folder:csv_latin1",
              "folder:png_decompression_bomb")


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("case", [c for c in fd.data_cases() if c.id in END_TO_END], ids=lambda c: c.id)
def test_data_mistake_stops_the_run_with_exit_2(case: fc.Case, tmp_path: Path, capsys):
    (tmp_path / "tiny.onnx").write_bytes(fc.onnx_model())
    (tmp_path / MATRIX).write_text(case.build(tmp_path))
    assert_exit_2(run_main(tmp_path, ["run", str(tmp_path / MATRIX)], capsys), case.culprit)
    assert not (case.marker and (tmp_path / "markers" / case.marker).exists()), "a payload in the data ran"


@pytest.mark.slow
def test_the_model_payloads_are_live(tmp_path: Path):
    """Loaded with the libraries' defaults, the .pt2 pickles and the TorchScript that writes a file do write
    their markers: their absence after a run is evidence."""
    import torch

    for name in ("pt2_weight", "pt2_constant"):
        (tmp_path / name).write_bytes(fm.hostile_pt2(tmp_path, name))
        try:
            torch.export.load(tmp_path / name)
        except Exception:  # a pickled weight is unpickled before the program is checked
            pass
        assert (tmp_path / "markers" / name).exists(), name
    (tmp_path / "writer.pt").write_bytes(fm.file_writer(tmp_path / "markers" / "ts_writer"))
    torch.jit.load(str(tmp_path / "writer.pt"))(torch.zeros(1, 3, 16, 16))
    assert (tmp_path / "markers" / "ts_writer").exists()


@dataclass
class Group:
    """One `run` of several broken or hostile models, one cell each; models `plan` refuses are left out."""

    project: Path
    cases: list[fc.Case]
    backends: list[str]
    refused: dict[str, str] = field(default_factory=dict)  # case id -> the matrix problem that names it
    records: dict[str, dict | None] = field(default_factory=dict)  # case id -> its cell's record
    text: str = ""  # everything plan and run printed
    code: int | None = None  # run's exit code

    def start(self, entries: dict[str, dict]) -> subprocess.Popen | None:
        """Plan the models in `entries` (case id -> model entry) until plan accepts them; run those."""
        kept = list(entries)
        while kept:
            models = [entries[i] | {"name": self.name(i)} for i in kept]
            exclude = [{"framework": "tensorflow", "backend": "onnxruntime"}]
            changes = ((("models",), models), (("axes", "backend"), self.backends), (("exclude",), exclude))
            (self.project / MATRIX).write_text(fc.render(changes))
            plan = cli(self.project, "plan", MATRIX)
            self.text += plan.stdout + plan.stderr
            named = {kept[int(m[1])]: line for line in plan.stderr.splitlines()
                     if (m := re.search(r"models\[(\d+)\]", line))}
            if plan.returncode != 2 or not named:
                return popen_cli(self.project, "run", MATRIX)
            self.refused.update(named)
            kept = [i for i in kept if i not in named]
        return None

    def finish(self, run: subprocess.Popen | None) -> None:
        if run is not None:
            self.text += run.communicate(timeout=600)[0]
            self.code = run.returncode
        report = cli(self.project, "report", "--format", "json")
        by_model = {r["cell"]["model"]: r for r in json.loads(report.stdout or "{}").get("records", [])}
        self.records = {case.id: by_model.get(self.name(case.id)) for case in self.cases}

    def name(self, case_id: str) -> str:
        """A name that says nothing of the case: a reason that names the model must not pass for one naming
        the file."""
        return f"m{[c.id for c in self.cases].index(case_id)}"


def build(*args: Path) -> subprocess.Popen:
    """`python fuzz_cases.py ARGS` (torch.export is not thread-safe, and TensorFlow is slow to import)."""
    script = str(fc.TESTS / "fuzz_model_cases.py")
    return subprocess.Popen([sys.executable, script, *map(str, args)], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "TF_CPP_MIN_LOG_LEVEL": "3"})


def built(child: subprocess.Popen) -> str:
    out, err = child.communicate(timeout=300)
    assert child.returncode == 0, f"building the model files failed:\n{err[-3000:]}"
    return out


def run_model_groups(torch_project: Path, other_project: Path) -> dict[str, Group]:
    """Two runs side by side: the PyTorch models; the ONNX and Keras models. Children build the files."""
    fc.write_project(torch_project)
    fc.write_project(other_project)
    torch_files, keras_files = build("torch", torch_project), build("keras", other_project)
    groups = [Group(torch_project, fm.torch_model_cases(), ["pytorch"]),
              Group(other_project, fm.onnx_and_keras_cases(), ["onnxruntime", "tensorflow"])]
    torch_run = groups[0].start(json.loads(built(torch_files)))
    built(keras_files)
    other_run = groups[1].start({case.id: case.build(other_project) for case in groups[1].cases})
    for group, run in zip(groups, (torch_run, other_run)):
        group.finish(run)
    return {case.id: group for group in groups for case in group.cases}


MODEL_TEST = "test_broken_or_hostile_model_fails_its_cells_naming_the_file"


@pytest.fixture(scope="module", autouse=True)
def model_runs(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    """When a model test is selected, its runs start with the module, in a thread: they take longest, and
    mostly wait on their children while the in-process tests run."""
    if not any(getattr(item, "originalname", "") == MODEL_TEST for item in request.session.items):
        yield None
        return
    projects = [tmp_path_factory.mktemp(name) for name in ("torch", "other")]  # not thread-safe: made here
    with ThreadPoolExecutor(1) as pool:
        yield pool.submit(run_model_groups, *projects)


@pytest.mark.slow
@pytest.mark.parametrize("case", fm.torch_model_cases() + fm.onnx_and_keras_cases(), ids=lambda c: c.id)
def test_broken_or_hostile_model_fails_its_cells_naming_the_file(case: fc.Case, model_runs: Future):
    group = model_runs.result()[case.id]
    assert_no_traceback(group.text)
    if case.id in group.refused:  # refused before running, naming the file: plan and run exit 2
        assert_told(group.refused[case.id], case.culprit)
    else:
        assert group.code == 0, f"run exited {group.code}:\n{group.text[-3000:]}"
        record = group.records[case.id]
        assert record is not None, f"no record:\n{group.text[-3000:]}"
        assert record["status"] == "failed", f"status {record['status']}: {record['reason']}"
        assert_told(record["reason"].split("\n  File ")[0], case.culprit)  # a stored reason may end in frames
    marker = case.marker and group.project / "markers" / case.marker
    assert not (marker and marker.exists()), "a payload in the model ran"
    read = [p for p in group.project.rglob("*") if p.is_file() and not p.is_symlink() and p.name != "secret"
            and fc.SECRET in p.read_bytes()]
    assert not read and fc.SECRET.decode() not in group.text, f"data outside the model's folder read: {read}"
