"""The conformance kit (bench_matrix.conformance): every installed built-in backend passes it, and backends
that break the contract fail it, each test naming the rule broken."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import pytest

from bench_matrix.conformance import BackendConformance
from bench_matrix.conformance.cases import Case, cases_of
from bench_matrix.conformance.here import Here
from bench_matrix.conformance.kit import Kit
from bench_matrix.registry import available

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import plugin_conformance_mutants  # noqa: E402
import plugin_conformance_zoo  # noqa: E402

pytest_plugins = ["bench_matrix.conformance.plugin"]  # a conftest.py would name the package

BUILT_IN = tuple(sorted(name for name, entry in available().items()
                        if entry.distribution.startswith("bench-matrix ")))
COMPILERS = ("aot_inductor", "torch_compile")  # an Inductor compile takes 10-20 s per model on 2 cores


class TestBuiltInBackends(BackendConformance):
    """The kit on every backend bench-matrix registers itself (cases this machine cannot run: one skip)."""

    backends = tuple(name for name in BUILT_IN if name not in COMPILERS)


class TestCompilers(BackendConformance):
    """PyTorch's compilers on the kit's model with two inputs and two outputs only, to keep CI short."""

    backends = tuple(name for name in BUILT_IN if name in COMPILERS)
    models = ("multi_io",)

    def test_runs_every_batch_size(self, case: Case, conformance_kit: Kit) -> None:
        """aot_inductor's package takes every batch to max_batch; torch_compile compiles again for each."""
        if case.backend == "torch_compile":
            pytest.skip("torch.compile compiles again for each new batch size (seconds each on 2 cores)")
        super().test_runs_every_batch_size(case, conformance_kit)


# What each zoo backend must fail with: the rules named by its failed tests (and nothing else).
BROKEN = {"good_ort": set(), "no_device": set(), "litters": {"convert-writes-only-out_dir"},
          "ignores_threads": {"threads-as-asked"}, "float64_out": {"fetch-returns-float32"},
          "drops_output": {"fetch-returns-every-output"}, "squeezes": {"batch-axis-first"},
          "nan_out": {"outputs-finite"}, "drifts": {"load-is-repeatable", "convert-is-repeatable"},
          "async_execute": {"execute-waits-for-its-work"},
          "bad_answers": {"probe-answers-reason-or-none", "option-reason-answers-reason-or-none",
                          "versions-names-libraries", "invalid-reason-agrees-with-supports",
                          "declares-devices"},
          "refuses": {"convert-succeeds"}, "keeps_out_dir": {"load-succeeds"},
          "path_in_meta": {"meta-is-json"}, "unloadable": {"backend-loads"},
          **plugin_conformance_mutants.RULES}


@pytest.fixture(scope="module")
def zoo_project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The zoo installed, and a test module checking it, enabled as a plugin package's tests would."""
    root = tmp_path_factory.mktemp("zoo")
    plugin_conformance_zoo.install(root / "site", plugin_conformance_mutants.MUTANTS)
    (root / "conftest.py").write_text('pytest_plugins = ["bench_matrix.conformance"]\n')
    (root / "test_zoo.py").write_text("from bench_matrix.conformance import BackendConformance\n\n\n"
                                      "class TestZoo(BackendConformance):\n"
                                      f"    backends = {tuple(BROKEN)!r}\n\n\n"
                                      "class TestOneModel(BackendConformance):\n"
                                      "    backends = ('good_ort',)\n"
                                      "    models = ('multi_io',)\n")
    return root


def _pytest(root: Path, plugin: object, *args: str) -> None:
    """pytest on root/test_zoo.py, in this process, with the zoo importable here and in fresh processes."""
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(root / "site"))
        patch.setenv("PYTHONPATH", os.pathsep.join([str(root / "site"), str(TESTS),
                                                    os.environ.get("PYTHONPATH", "")]))
        pytest.main([str(root / "test_zoo.py"), "-q", "--tb=line", "-p", "no:cacheprovider", "--basetemp",
                     str(root / "tmp"), *args], plugins=[plugin])


class Collected:
    """The node ids pytest collects."""

    def __init__(self) -> None:
        self.nodeids: list[str] = []

    def pytest_collection_finish(self, session: pytest.Session) -> None:
        self.nodeids.extend(item.nodeid for item in session.items)


@pytest.fixture(scope="module")
def zoo(zoo_project: Path) -> list[pytest.TestReport]:
    """The report of every test phase of the kit run on the zoo."""
    reports: list[pytest.TestReport] = []

    class Collect:
        def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
            reports.append(report)

    _pytest(zoo_project, Collect())
    return reports


def _backend(report: pytest.TestReport) -> str:
    """The zoo backend a report's test checks; "one_model" for every test of TestOneModel, "" for a test of
    no backend."""
    if "TestOneModel" in report.nodeid:
        return "one_model"
    found = re.search(r"\[([a-z0-9_]+)", report.nodeid)
    return found.group(1) if found else ""


@pytest.mark.parametrize("backend", list(BROKEN))
def test_each_broken_rule_is_named(backend: str, zoo: list[pytest.TestReport]) -> None:
    failed = [r.longreprtext for r in zoo if r.failed and _backend(r) == backend]
    named = {rule for text in failed for rule in re.findall(r"rule ([a-z0-9_-]+):", text)}
    assert named == BROKEN[backend], failed


def test_writes_outside_out_dir_are_listed(zoo: list[pytest.TestReport]) -> None:
    text = next(r.longreprtext for r in zoo if r.failed and "writes_only" in r.nodeid)
    assert all(name in text for name in ("cwd/convert.log", "home/.zoo-marker", ".zoo-cache")), text


def test_cases_this_machine_cannot_run_get_no_tests_and_one_skip_with_the_probe_reason(
        zoo: list[pytest.TestReport]) -> None:
    assert not [r.nodeid for r in zoo if _backend(r) == "no_device" and "-npu-" in r.nodeid]
    calls = {r.nodeid.split("::")[1]: r for r in zoo
             if r.nodeid.endswith("::test_cases_not_run_here") and r.when == "call"}
    assert calls["TestZoo"].skipped and calls["TestZoo"].longrepr[2] == (
        "Skipped: 3 cases not run on this machine (no tests generated), by reason:\n"
        "- 3 cases (no_device on npu): no NPU on this machine (the zoo's probe)")
    assert calls["TestOneModel"].passed  # it runs every case of good_ort


def test_the_terminal_summary_says_once_what_is_not_run(zoo_project: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Each probe question is asked once, at collection, however many cases and classes share it."""
    capsys.readouterr()
    plugin_conformance_zoo.PROBED.clear()
    _pytest(zoo_project, collect := Collected(), "--collect-only", "--bench-matrix-backend", "no_device")
    out = capsys.readouterr().out
    assert plugin_conformance_zoo.PROBED == [("npu", "fp32")]
    unwanted = [nodeid for nodeid in collect.nodeids if "-npu-" in nodeid or "NOTSET" in nodeid]
    assert collect.nodeids and not unwanted, collect.nodeids
    assert out.count("no NPU on this machine") == 1 and "bench-matrix conformance kit" in out, out
    assert "3 cases (no_device on npu): no NPU on this machine (the zoo's probe)" in out, out


def test_a_probe_that_raises_is_the_reason_its_cases_are_not_run() -> None:
    class Raises(plugin_conformance_zoo.NoDevice):
        def probe(self, target: str, precision: str) -> str | None:
            raise RuntimeError("the driver API is missing")

    backend = Raises()
    (case,) = cases_of(backend, ("regression",))
    reason = Here().reason(backend, case)
    assert reason == "probe('npu', 'fp32') raised RuntimeError: the driver API is missing"


def test_the_command_line_narrows_the_backends_checked(zoo_project: Path) -> None:
    _pytest(zoo_project, collect := Collected(), "--collect-only", "--bench-matrix-backend", "good_ort")
    cases = [nodeid for nodeid in collect.nodeids if "[" in nodeid]
    assert cases and all("[good_ort" in nodeid for nodeid in cases), collect.nodeids


def test_a_class_chooses_the_models_its_cases_run_on(zoo: list[pytest.TestReport]) -> None:
    cases = {r.nodeid for r in zoo if _backend(r) == "one_model" and "-cpu-" in r.nodeid and r.passed}
    assert cases and all(nodeid.endswith("-multi_io]") for nodeid in cases), cases


def test_the_kit_leaves_other_tests_parametrized_by_case_alone(tmp_path: Path) -> None:
    """A plugin package's own tests may name a parameter `case` too: the kit deselects only its own."""
    (tmp_path / "conftest.py").write_text('pytest_plugins = ["bench_matrix.conformance"]\n')
    (tmp_path / "test_own_cases.py").write_text("import pytest\n\n\n@pytest.mark.parametrize('case', [1, 2])\n"
                                                "def test_own(case):\n    assert case\n")
    pytest.main([str(tmp_path / "test_own_cases.py"), "-q", "--collect-only", "-p", "no:cacheprovider"],
                plugins=[collect := Collected()])
    assert [nodeid.split("::")[-1] for nodeid in collect.nodeids] == ["test_own[1]", "test_own[2]"]
