"""The pytest side of the kit: the --bench-matrix-backend option, one test per backend or per case this
machine runs of every BackendConformance subclass, the cases it cannot run reported once (a skipped test per
class and the terminal summary), and the kit each such class shares between its tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench_matrix.conformance.cases import Case
from bench_matrix.conformance.here import Here, NotRun, describe
from bench_matrix.conformance.kit import Kit
from bench_matrix.conformance.suite import ONCE_PER_COMBINATION, BackendConformance

OPTION = "--bench-matrix-backend"
HERE = pytest.StashKey[Here]()
SELECTED = pytest.StashKey[NotRun]()  # the cases not run of the classes whose tests were selected


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(OPTION, action="append", default=None, metavar="NAME", dest="bench_matrix_backends",
                     help="check only this backend with the bench-matrix conformance kit (repeatable)")


def checked_backends(config: pytest.Config, cls: type[BackendConformance]) -> list[str]:
    """The class's backends, or those the command line names."""
    return list(config.getoption("bench_matrix_backends", default=None) or cls.backends)


def split(config: pytest.Config, cls: type[BackendConformance]) -> tuple[list[Case], NotRun]:
    """The cases of the class's backends that this machine runs, and the others with why not (asked once)."""
    here = config.stash.setdefault(HERE, Here())
    return here.split(tuple(checked_backends(config, cls)), cls.models)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    cls = metafunc.cls
    if cls is None or not issubclass(cls, BackendConformance):
        return
    if "backend_name" in metafunc.fixturenames:
        metafunc.parametrize("backend_name", checked_backends(metafunc.config, cls))
    if "case" in metafunc.fixturenames:
        cases = split(metafunc.config, cls)[0]
        if metafunc.function.__name__ in ONCE_PER_COMBINATION:
            cases = [case for case in cases if case.model == cls.models[0]]
        metafunc.parametrize("case", cases, ids=[case.id for case in cases])


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A case test of a class with no case to run here (pytest's empty parameter set) is deselected, not
    skipped: test_cases_not_run_here says why."""
    empty = [item for item in items if _without_case(item)]
    if empty:
        config.hook.pytest_deselected(items=empty)
        items[:] = [item for item in items if not _without_case(item)]


def _without_case(item: pytest.Item) -> bool:
    """Whether a kit class's case test got pytest's empty parameter set (other tests' `case` is theirs)."""
    cls = getattr(item, "cls", None)
    if not (isinstance(cls, type) and issubclass(cls, BackendConformance)):
        return False
    params = getattr(getattr(item, "callspec", None), "params", {})
    return "case" in params and not isinstance(params["case"], Case)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Keep, for the terminal summary, the cases not run of every kit class with a test selected."""
    classes = [cls for cls in dict.fromkeys(getattr(item, "cls", None) for item in session.items)
               if isinstance(cls, type) and issubclass(cls, BackendConformance)]
    not_run = {case: reason for cls in classes for case, reason in split(session.config, cls)[1]}
    session.config.stash[SELECTED] = list(not_run.items())


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, config: pytest.Config) -> None:
    if not_run := config.stash.get(SELECTED, []):
        terminalreporter.write_sep("=", "bench-matrix conformance kit")
        terminalreporter.write_line(describe(not_run))


@pytest.fixture
def cases_not_run(request: pytest.FixtureRequest) -> NotRun:
    """The cases of the test's class this machine cannot run, each with why (decided at collection)."""
    return split(request.config, request.cls)[1]


@pytest.fixture(scope="class")
def conformance_kit(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Kit:
    """The kit of one BackendConformance subclass: its models, artifacts and sessions, made once."""
    root: Path = tmp_path_factory.mktemp("conformance")
    return Kit(root, request.cls.backend_options, request.cls.models[0])
