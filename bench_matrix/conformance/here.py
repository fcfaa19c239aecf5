"""Which cases this machine can run, decided once at collection from each backend's own answers (each distinct
question asked once), and the others grouped by reason, to be reported once instead of skipped one by one."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from bench_matrix.backend import Backend
from bench_matrix.conformance.cases import Case, cases_of
from bench_matrix.conformance.models import BUILDERS
from bench_matrix.strategy import StrategySpec
from bench_matrix.registry import BackendLoadError, load_backend

NotRun = list[tuple[Case, str]]  # cases this machine cannot run, each with why


class Here:
    """What this machine runs of the cases of some backends; every answer a backend gives is asked once."""

    def __init__(self) -> None:
        self._answers: dict[tuple[Any, ...], Any] = {}

    def _once(self, key: tuple[Any, ...], ask: Callable[[], Any]) -> Any:
        if key not in self._answers:
            self._answers[key] = ask()
        return self._answers[key]

    def backend(self, name: str) -> Backend | None:
        """The backend, or None if it does not load (its test_backend_loads_and_declares says why)."""
        def load() -> Backend | None:
            try:
                return load_backend(name)
            except BackendLoadError:
                return None

        return self._once(("backend", name), load)

    def split(self, names: tuple[str, ...], models: tuple[str, ...]) -> tuple[list[Case], NotRun]:
        """The cases of the named backends on `models` that this machine runs, and the others with why not."""
        return self._once(("split", names, models), lambda: self._split(names, models))

    def _split(self, names: tuple[str, ...], models: tuple[str, ...]) -> tuple[list[Case], NotRun]:
        runs: list[Case] = []
        not_run: NotRun = []
        for backend in filter(None, map(self.backend, names)):
            for case in cases_of(backend, models):
                if reason := self.reason(backend, case):
                    not_run.append((case, reason))
                else:
                    runs.append(case)
        return runs, not_run

    def reason(self, backend: Backend, case: Case) -> str | None:
        """Why this machine cannot run the case, or None: the kit has no model of its framework, the backend
        refuses it for the kit's model, or its probes give a reason."""
        if case.framework not in BUILDERS:
            return f"the conformance kit has no {case.framework} models (it has {', '.join(BUILDERS)})"
        source_format = BUILDERS[case.framework][1]
        combination = (case.framework, case.strategy, case.precision, case.target)
        step = StrategySpec(case.strategy, case.strategy)
        if invalid := (self._ask(backend, "invalid_reason", combination)
                       or self._ask(backend, "option_reason", (case.strategy, source_format),
                                    lambda: backend.option_reason(step, source_format))):
            return f"not valid for the kit's {source_format} model: {invalid}"
        reasons = (self._ask(backend, "probe", (case.target, case.precision)),
                   self._ask(backend, "probe_source", (case.framework, source_format)),
                   backend.convert_needs_reason(*combination))
        return "; ".join(r for r in reasons if r) or None

    def _ask(self, backend: Backend, method: str, args: tuple[str, ...],
             call: Callable[[], Any] | None = None) -> str | None:
        """backend.method(*args)'s reason, or None; raising is a reason too (and breaks the method's rule)."""
        def ask() -> str | None:
            try:
                answer = call() if call else getattr(backend, method)(*args)
            except Exception as exc:
                return f"{method}({', '.join(map(repr, args))}) raised {type(exc).__name__}: {exc}"
            return str(answer) if answer else None

        return self._once((backend.name, method, *args), ask)


def describe(not_run: NotRun) -> str:
    """How many cases this machine does not run, then one line per reason: how many, of which backends on
    which targets, and the reason."""
    return "\n".join([f"{_count(len(not_run))} not run on this machine (no tests generated), by reason:",
                      *(f"- {line}" for line in summary(not_run))])


def summary(not_run: NotRun) -> list[str]:
    """One line per reason: how many cases, of which backends on which targets, and the reason."""
    grouped: dict[str, dict[str, dict[str, None]]] = {}
    counts: dict[str, int] = {}
    for case, reason in not_run:
        grouped.setdefault(reason, {}).setdefault(case.backend, {})[case.target] = None
        counts[reason] = counts.get(reason, 0) + 1
    return [f"{_count(counts[reason])} ({_where(targets)}): {reason}" for reason, targets in grouped.items()]


def _where(targets: dict[str, dict[str, None]]) -> str:
    """E.g. 'onnxruntime on cuda; openvino on intel_gpu, intel_npu'."""
    return "; ".join(f"{backend} on {', '.join(names)}" for backend, names in targets.items())


def _count(count: int) -> str:
    return f"{count} case{'' if count == 1 else 's'}"
