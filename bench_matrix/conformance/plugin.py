"""The pytest side of the kit: the --bench-matrix-backend option, one test per backend or per case of every
BackendConformance subclass, and the kit each such class shares between its tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench_matrix.backends.registry import BackendLoadError, load_backend
from bench_matrix.conformance.cases import Case, cases_of
from bench_matrix.conformance.kit import Kit
from bench_matrix.conformance.suite import ONCE_PER_COMBINATION, BackendConformance

OPTION = "--bench-matrix-backend"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(OPTION, action="append", default=None, metavar="NAME", dest="bench_matrix_backends",
                     help="check only this backend with the bench-matrix conformance kit (repeatable)")


def checked_backends(config: pytest.Config, cls: type[BackendConformance]) -> list[str]:
    """The class's backends, or those the command line names."""
    return list(config.getoption("bench_matrix_backends", default=None) or cls.backends)


def _cases(names: list[str], models: tuple[str, ...]) -> list[Case]:
    """Every case of the named backends that import (the others fail test_backend_loads_and_declares)."""
    found = []
    for name in names:
        try:
            found += cases_of(load_backend(name), models)
        except BackendLoadError:
            continue
    return found


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    cls = metafunc.cls
    if cls is None or not issubclass(cls, BackendConformance):
        return
    names = checked_backends(metafunc.config, cls)
    if "backend_name" in metafunc.fixturenames:
        metafunc.parametrize("backend_name", names)
    if "case" in metafunc.fixturenames:
        cases = _cases(names, cls.models)
        if metafunc.function.__name__ in ONCE_PER_COMBINATION:
            cases = [case for case in cases if case.model == cls.models[0]]
        metafunc.parametrize("case", cases, ids=[case.id for case in cases])


@pytest.fixture(scope="class")
def conformance_kit(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Kit:
    """The kit of one BackendConformance subclass: its models, artifacts and sessions, made once."""
    root: Path = tmp_path_factory.mktemp("conformance")
    return Kit(root, request.cls.backend_options)
