"""The kit's state: backends, models, artifacts and sessions, each made once and shared by every test of a
case; a failure or skip is kept too, so each later test of the case reports it."""

from __future__ import annotations

import contextlib
import json
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest

from bench_matrix.backend import Backend, ConvertRequest, Session
from bench_matrix.conformance.cases import Case, RuleBroken
from bench_matrix.conformance.checks import check_fetched, check_order, check_this_call, reported_threads
from bench_matrix.conformance.concurrency import oversubscribed
from bench_matrix.conformance.fresh import infos
from bench_matrix.conformance.models import LARGE, THREADS, KitModel, build
from bench_matrix.conformance.watch import watched
from bench_matrix.strategy import StrategySpec
from bench_matrix.registry import BackendLoadError, load_backend
from bench_matrix.tensors import Inputs, count, take

T = TypeVar("T")
Previous = tuple[int | None, list[np.ndarray] | None]  # a session's call before: its batch and reference


@contextlib.contextmanager
def hidden(folder: Path) -> Iterator[None]:
    """`folder` renamed out of reach in the body (if it exists), then back."""
    away = folder.with_name(folder.name + ".hidden")
    moved = folder.exists()
    if moved:
        folder.rename(away)
    try:
        yield
    finally:
        if moved:
            away.rename(folder)


@dataclass
class Artifact:
    """A converted artifact: its final directory (renamed there after convert, as the runner does), the
    metadata as stored (through JSON), and what the conversion wrote outside its output directory."""

    directory: Path
    meta: dict[str, Any]
    writes: list[str] = field(default_factory=list)


@dataclass
class Loaded:
    """A session of a case's first artifact, with its info() taken right after loading."""

    session: Session
    info: Any


class Kit:
    """Makes each thing once per test class, under `root`; `options` are backend options by backend name;
    threads are counted while the cases of model `sampled` run (None: every model's)."""

    def __init__(self, root: Path, options: dict[str, dict[str, Any]] | None = None,
                 sampled: str | None = None):
        self.root = root
        self.options = options or {}
        self.sampled = sampled
        self._outcomes: dict[Any, tuple[bool, Any]] = {}
        self._fresh: dict[str, dict[str, Any]] = {}
        self._previous: dict[int, tuple[Session, Previous]] = {}  # by id: each session's call before

    def _once(self, key: Any, make: Callable[[], T]) -> T:
        """make()'s value, or the exception it raised (a skip included), for `key` at every call."""
        if key not in self._outcomes:
            try:
                self._outcomes[key] = (True, make())
            except (Exception, pytest.skip.Exception) as exc:
                self._outcomes[key] = (False, (exc, exc.__traceback__))
        made, value = self._outcomes[key]
        if not made:
            exc, traceback = value
            raise exc.with_traceback(traceback)  # not the traceback of every earlier raise as well
        return value

    def backend(self, name: str) -> Backend:
        def make() -> Backend:
            try:
                return load_backend(name)
            except BackendLoadError as exc:
                raise RuleBroken("backend-loads", str(exc)) from exc

        return self._once(("backend", name), make)

    def model(self, framework: str, name: str) -> KitModel:
        def make() -> KitModel:
            try:
                return build(framework, name, self.root / "models" / framework)
            except ImportError as exc:
                pytest.skip(f"the kit's {framework} models cannot be built here: {exc}")

        return self._once(("model", framework, name), make)

    def artifact(self, case: Case, which: str = "first") -> Artifact:
        """The case's artifact `which`: "first", or "second" (converted again, to compare)."""
        return self._once(("artifact", case, which), lambda: self._convert(case, which))

    def _convert(self, case: Case, which: str) -> Artifact:
        backend, model = self.backend(case.backend), self.model(case.framework, case.model)
        place = self.root / "artifacts" / case.id
        out = place / f"{which}.tmp" / "model"
        out.mkdir(parents=True)
        shared = self._shared(case)
        shared.mkdir(parents=True, exist_ok=True)
        request = ConvertRequest(source=model.source, step=StrategySpec(case.strategy, case.strategy),
                                 precision=case.precision, target=case.target, out_dir=out,
                                 calibration=lambda n: take(model.calibration, slice(0, n)), threads=THREADS,
                                 seed=0, shared_dir=shared, max_batch=LARGE,
                                 options=dict(self.options.get(case.backend, {})))
        with watched(place / f"{which}.watch", model.source.path.parent) as writes:
            try:
                meta = backend.convert(request)
            except Exception as exc:
                raise RuleBroken("convert-succeeds", f"convert() raised {type(exc).__name__}: {exc}") from exc
        try:
            stored = json.loads(json.dumps(meta))
        except (TypeError, ValueError) as exc:
            raise RuleBroken("meta-is-json", f"convert() returned metadata JSON cannot hold: {exc}") from exc
        if not any(out.iterdir()):
            raise RuleBroken("convert-writes-artifact", f"convert() wrote nothing into out_dir {out}")
        final = place / which
        out.parent.rename(final)
        return Artifact(final / "model", stored, writes)

    def _shared(self, case: Case) -> Path:
        return self.root / "shared" / case.backend / f"{case.framework}-{case.model}"

    def load(self, case: Case, which: str = "first") -> Session:
        """A new session of the case's artifact `which`, loaded with THREADS threads while the conversion's
        shared_dir is out of reach: the artifact is its out_dir alone."""
        artifact = self.artifact(case, which)
        backend = self.backend(case.backend)
        args = (artifact.directory, artifact.meta, case.target, case.precision, THREADS)
        try:
            with hidden(self._shared(case)):
                return backend.load(*args)
        except Exception as exc:
            try:
                backend.load(*args)
            except Exception:
                raise RuleBroken("load-succeeds", f"load() raised {type(exc).__name__}: {exc}") from exc
            raise RuleBroken("artifact-lives-in-out_dir",
                             f"load() raised {type(exc).__name__}: {exc} while shared_dir was out of reach, "
                             f"and works with it: the artifact must be whole in out_dir (it alone is stored, "
                             f"measured and shipped)") from exc

    def run(self, session: Session, inputs: Inputs, wanted: list[np.ndarray],
            allowed: list[np.ndarray]) -> list[np.ndarray]:
        """The session's outputs on `inputs`, checked as fetch must give them, in model order, as this call's,
        not the last's (`wanted`: the inputs' fp32 reference; `allowed`: the precision's bounds)."""
        previous = self.ran(session, count(inputs), wanted)
        try:
            outputs = session.predict(inputs)
        except Exception as exc:
            raise RuleBroken("session-runs", f"prepare/execute/fetch raised {type(exc).__name__}: {exc}") \
                from exc
        check_fetched(outputs, wanted, previous[0])
        check_order(outputs, wanted, allowed)
        check_this_call(outputs, wanted, previous[1], allowed)
        return outputs

    def ran(self, session: Session, batch: int, wanted: list[np.ndarray] | None = None) -> Previous:
        """Note that `session` runs a batch of `batch` now (whose reference is `wanted`, if known); what was
        noted of its call before."""
        previous = self._previous.get(id(session), (session, (None, None)))[1]
        self._previous[id(session)] = (session, (batch, wanted))
        return previous

    def loaded(self, case: Case) -> Loaded:
        """The case's first artifact, loaded once for the tests that only run it."""
        def make() -> Loaded:
            session = self.load(case)
            return Loaded(session, session.info())

        return self._once(("loaded", case), make)

    def reloaded(self, case: Case) -> Session:
        """A second session of the case's first artifact, loaded once for the tests that compare two loads or
        need a session no other test ran first."""
        return self._once(("reloaded", case), lambda: self.load(case))

    def fresh_info(self, case: Case) -> dict[str, Any]:
        """The case's first artifact in a fresh process: info() and, on CPU, its `oversubscribed` share
        (else {"error": ...}); one process serves all loaded cases whose info() here shows other threads."""
        self.loaded(case)
        if case.id not in self._fresh:
            scratch = self.root / "fresh"
            shutil.rmtree(scratch, ignore_errors=True)
            scratch.mkdir()
            cases = [key[1] for key, (made, value) in self._outcomes.items()
                     if key[0] == "loaded" and made and key[1].id not in self._fresh
                     and reported_threads(value.info, THREADS) is not None]
            jobs = [{"case": c.id, "backend": c.backend, "artifact": str(self.artifact(c).directory),
                     "meta": self.artifact(c).meta, "target": c.target, "precision": c.precision,
                     "threads": THREADS, "inputs": self._inputs_file(c, scratch)} for c in cases]
            self._fresh.update(infos(jobs, THREADS, scratch))
        return self._fresh[case.id]

    def oversubscribed(self, case: Case) -> float | None:
        """In this process, the share of samples with more threads running than asked while the case's session
        ran the large batch; None off the CPU, for an unsampled model, or where the system does not tell."""
        if not self._sampled(case):
            return None
        session, large = self.loaded(case).session, self.model(case.framework, case.model).large
        self.ran(session, count(large))
        try:
            prepared = session.prepare(large)
            return oversubscribed(lambda: session.fetch(session.execute(prepared)), THREADS)
        except Exception as exc:
            raise RuleBroken("session-runs", f"prepare/execute/fetch raised {type(exc).__name__}: {exc}") \
                from exc

    def _sampled(self, case: Case) -> bool:
        """Whether the case's threads are counted: on the CPU, for the model sampled (where a runtime runs
        its threads does not depend on the model)."""
        return self.sampled in (None, case.model) and self.backend(case.backend).device(case.target) == "cpu"

    def _inputs_file(self, case: Case, scratch: Path) -> str | None:
        """The case's model's large batch saved in `scratch` for a fresh process; None if not sampled."""
        if not self._sampled(case):
            return None
        path = scratch / f"{case.framework}-{case.model}.npz"
        if not path.exists():
            np.savez(path, **self.model(case.framework, case.model).large)
        return str(path)
