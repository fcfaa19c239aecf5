"""The conformance tests: subclass BackendConformance in a test module, naming the backends it checks."""

from __future__ import annotations

import json
from typing import Any, ClassVar

import pytest

from bench_matrix.backend import DEVICES, Session, Support
from bench_matrix.conformance.cases import REPEAT, SOURCE_FORMATS, TOLERANCES, Case, RuleBroken, Tolerance, \
    combinations, option_variants, reason_problem
from bench_matrix.conformance.checks import bounds, check_close, check_kept, check_profile, \
    check_quantised, pending_work, reported_threads
from bench_matrix.conformance.here import NotRun, describe
from bench_matrix.conformance.kit import Kit
from bench_matrix.conformance.models import BATCHES, LARGE, MODELS, THREADS
from bench_matrix.strategy import StrategySpec
from bench_matrix.tensors import take

AXES = ("frameworks", "strategies", "precisions", "targets")
# Tests run on the first of the class's models only: converting a second time costs most of a case's time, and
# where a conversion writes does not depend on the model; the first model (regression) has the BatchNorm that
# every batch size is checked through.
ONCE_PER_COMBINATION = ("test_convert_is_repeatable", "test_convert_writes_only_into_out_dir",
                        "test_runs_every_batch_size")
# threads-as-asked: more threads than asked may run in at most this share of the samples taken while the
# session executes (a runtime that keeps to one thread: 0-11 %; one that ignores it: about 100 %)
OVERSUBSCRIBED = 0.5


def _answer(rule: str, call: str, method: Any, *args: Any) -> None:
    """Call a reason-giving method (`call` shows how, in the message); RuleBroken unless it answers a
    non-empty str or None."""
    try:
        answer = method(*args)
    except Exception as exc:
        raise RuleBroken(rule, f"{call} raised {type(exc).__name__}: {exc}") from exc
    if problem := reason_problem(answer, call):
        raise RuleBroken(rule, problem)


def _names(values: Any) -> bool:
    return isinstance(values, tuple) and bool(values) and all(isinstance(v, str) and v for v in values)


def _devices_problem(devices: Any, targets: set[str]) -> str | None:
    """Why `devices` does not map targets the backend declares to DEVICES, or None."""
    if not isinstance(devices, dict):
        return f"devices is {devices!r}, not a dict of target -> device"
    for target, device in devices.items():
        if target not in targets:
            return f"devices names {target!r}, a target no Support declares ({', '.join(sorted(targets))})"
        if device not in DEVICES:
            return f"devices[{target!r}] is {device!r}; a device is one of {', '.join(DEVICES)}"
    return None


class BackendConformance:
    """The contract every backend keeps, checked on the kit's models for every combination it declares. A
    test module subclasses it (as Test...) with `backends` set; `--bench-matrix-backend NAME` narrows it."""

    backends: ClassVar[tuple[str, ...]] = ()
    # the kit's models each combination runs on; the first also converts a second time
    models: ClassVar[tuple[str, ...]] = MODELS
    # each backend's `backend_options`, as a matrix would give them
    backend_options: ClassVar[dict[str, dict[str, Any]]] = {}
    # per precision, over TOLERANCES: a backend's own precisions need one
    tolerances: ClassVar[dict[str, Tolerance]] = {}

    def _tolerance(self, precision: str) -> Tolerance:
        found = {**TOLERANCES, **self.tolerances}.get(precision)
        if found is None:
            raise RuleBroken("outputs-within-tolerance",
                             f"no tolerance is stated for precision {precision!r}: give one in `tolerances`")
        return found

    def test_backend_loads_and_declares(self, backend_name: str, conformance_kit: Kit) -> None:
        backend = conformance_kit.backend(backend_name)
        if not (isinstance(backend.description, str) and backend.description.strip()):
            raise RuleBroken("declares-supports", f"description is {backend.description!r}, not text")
        supports = backend.supports
        if not (isinstance(supports, tuple) and supports and all(isinstance(s, Support) for s in supports)):
            raise RuleBroken("declares-supports", f"supports is {supports!r}, not a tuple of Support")
        for s, axis in ((s, axis) for s in supports for axis in AXES):
            if not _names(getattr(s, axis)):
                raise RuleBroken("declares-supports", f"{s!r}: {axis} is not a non-empty tuple of names")
        for s in supports:
            needs = s.convert_needs
            if not (isinstance(needs, tuple) and all(isinstance(m, str) and m for m in needs)):
                raise RuleBroken("declares-supports", f"{s!r}: convert_needs is not a tuple of module names")
        if problem := _devices_problem(backend.devices, {t for s in supports for t in s.targets}):
            raise RuleBroken("declares-devices", problem)

    def test_versions_name_libraries(self, backend_name: str, conformance_kit: Kit) -> None:
        versions = conformance_kit.backend(backend_name).versions()
        if not (isinstance(versions, dict) and _names(tuple(versions)) and _names(tuple(versions.values()))):
            raise RuleBroken("versions-names-libraries", f"versions() returned {versions!r}, not a non-empty "
                                                         f"dict of library name -> version")

    def test_probes_answer_reason_or_none(self, backend_name: str, conformance_kit: Kit) -> None:
        backend, rule = conformance_kit.backend(backend_name), "probe-answers-reason-or-none"
        for framework, _, precision, target in combinations(backend):
            _answer(rule, f"probe({target!r}, {precision!r})", backend.probe, target, precision)
            for fmt in SOURCE_FORMATS.get(framework, (framework,)):
                _answer(rule, f"probe_source({framework!r}, {fmt!r})", backend.probe_source, framework, fmt)

    def test_option_reason_answers_reason_or_none(self, backend_name: str, conformance_kit: Kit) -> None:
        backend, rule = conformance_kit.backend(backend_name), "option-reason-answers-reason-or-none"
        for framework, kind in sorted({(f, st) for f, st, _, _ in combinations(backend)}):
            for fmt in SOURCE_FORMATS.get(framework, (framework,)):
                for options in option_variants(kind):
                    _answer(rule, f"option_reason({kind!r} {options}, {fmt!r})", backend.option_reason,
                            StrategySpec(kind, kind, options), fmt)

    def test_invalid_reason_agrees_with_supports(self, backend_name: str, conformance_kit: Kit) -> None:
        backend, rule = conformance_kit.backend(backend_name), "invalid-reason-agrees-with-supports"
        for combo in combinations(backend):
            if (reason := backend.invalid_reason(*combo)) is not None:
                raise RuleBroken(rule, f"invalid_reason{combo} refuses a declared combination: {reason}")
        undeclared = ("no-such-framework", "none", "fp32", "cpu")
        reason = backend.invalid_reason(*undeclared)
        if not (isinstance(reason, str) and reason.strip()):
            raise RuleBroken(rule, f"invalid_reason{undeclared} returned {reason!r}, not why it is not "
                                   f"declared")

    def test_cases_not_run_here(self, cases_not_run: NotRun) -> None:
        """Skipped, saying once which cases this machine cannot run and why: they get no tests here."""
        if cases_not_run:
            pytest.skip(describe(cases_not_run))

    def test_converts(self, case: Case, conformance_kit: Kit) -> None:
        conformance_kit.artifact(case)

    def test_outputs_match_the_reference(self, case: Case, conformance_kit: Kit) -> None:
        model = conformance_kit.model(case.framework, case.model)
        tolerance = self._tolerance(case.precision)
        allowed = bounds(tolerance, model.reference)
        session = conformance_kit.loaded(case).session
        outputs = conformance_kit.run(session, model.eval, model.reference, allowed)
        if case.precision == "int8":
            check_quantised(outputs, model.reference, bounds(REPEAT, model.reference))
        check_close(outputs, model.reference, allowed, "outputs-within-tolerance",
                    f"the {case.framework} model's own fp32 outputs (allowed at {case.precision}: "
                    f"{tolerance.factor:g} x {tolerance.basis})")

    def test_runs_a_batch_of_one(self, case: Case, conformance_kit: Kit) -> None:
        model = conformance_kit.model(case.framework, case.model)
        first = [out[:1] for out in model.reference]
        allowed = bounds(self._tolerance(case.precision), model.reference)
        session = conformance_kit.loaded(case).session
        outputs = conformance_kit.run(session, take(model.eval, slice(0, 1)), first, allowed)
        check_close(outputs, first, allowed, "runs-any-batch", "the fp32 reference of the same sample")

    def test_runs_every_batch_size(self, case: Case, conformance_kit: Kit) -> None:
        """Each size class of batch from 1 to max_batch (BATCHES), one after another in one session (the
        first model only)."""
        model = conformance_kit.model(case.framework, case.model)
        allowed = bounds(self._tolerance(case.precision), model.large_reference)
        session = conformance_kit.loaded(case).session
        for n in BATCHES:
            wanted = [out[:n] for out in model.large_reference]
            outputs = conformance_kit.run(session, take(model.large, slice(0, n)), wanted, allowed)
            check_close(outputs, wanted, allowed, "runs-any-batch",
                        f"the fp32 reference at batch {n} (max_batch {LARGE})")

    def test_each_call_gives_its_own_outputs(self, case: Case, conformance_kit: Kit) -> None:
        """A second session called on the large batch, then on it reversed (same size: a reused buffer is the
        same); the second call gives its own outputs, and the first call's arrays stay as they were."""
        model, backwards = conformance_kit.model(case.framework, case.model), slice(None, None, -1)
        session = conformance_kit.reloaded(case)
        allowed = bounds(self._tolerance(case.precision), model.large_reference)
        first = conformance_kit.run(session, model.large, model.large_reference, allowed)
        kept = [out.copy() for out in first]
        conformance_kit.run(session, take(model.large, backwards), [out[backwards] for out in
                                                                     model.large_reference], allowed)
        check_kept(first, kept)

    def test_execute_returns_when_done(self, case: Case, conformance_kit: Kit) -> None:
        model = conformance_kit.model(case.framework, case.model)
        session = conformance_kit.loaded(case).session
        conformance_kit.ran(session, LARGE)
        try:
            reason = pending_work(session, model.large)
        except Exception as exc:
            raise RuleBroken("session-runs", f"prepare/execute/fetch raised {type(exc).__name__}: {exc}") \
                from exc
        if reason:
            raise RuleBroken("execute-waits-for-its-work", reason)

    def test_info_is_json(self, case: Case, conformance_kit: Kit) -> None:
        info = conformance_kit.loaded(case).info
        try:
            json.dumps(info)
        except (TypeError, ValueError) as exc:
            raise RuleBroken("info-is-json", f"info() returned {info!r}; JSON cannot hold it: {exc}") \
                from exc

    def test_threads_as_asked(self, case: Case, conformance_kit: Kit) -> None:
        """info() reports them, and no more threads run at once than asked while the session executes: seen
        in this process, or else in a fresh one (a runtime may set its threads once per process)."""
        if reported_threads(conformance_kit.loaded(case).info, THREADS) is None:
            share = conformance_kit.oversubscribed(case)
        else:
            fresh = conformance_kit.fresh_info(case)
            if "error" in fresh:
                raise RuleBroken("threads-as-asked", f"loading in a fresh process failed: {fresh['error']}")
            if problem := reported_threads(fresh["info"], THREADS):
                raise RuleBroken("threads-as-asked", f"{problem} (in a fresh process)")
            share = fresh.get("oversubscribed")
        if share is not None and share > OVERSUBSCRIBED:
            raise RuleBroken("threads-as-asked", f"asked for {THREADS} thread(s), more ran at once in "
                                                 f"{share:.0%} of the moments sampled while execute ran: the "
                                                 f"runtime does not keep to `threads`")

    def test_profile_is_plausible(self, case: Case, conformance_kit: Kit) -> None:
        """A session implementing Session.profile (optional: the default's reason is not checked)."""
        session = conformance_kit.loaded(case).session
        if type(session).profile is not Session.profile:
            model = conformance_kit.model(case.framework, case.model)
            check_profile(session, take(model.eval, slice(0, 1)), case.precision)

    def test_load_is_repeatable(self, case: Case, conformance_kit: Kit) -> None:
        self._same_as_first(case, conformance_kit, conformance_kit.reloaded(case), "load-is-repeatable",
                            "the first load's outputs")

    def test_convert_is_repeatable(self, case: Case, conformance_kit: Kit) -> None:
        second = conformance_kit.load(case, "second")
        self._same_as_first(case, conformance_kit, second, "convert-is-repeatable",
                            "the outputs of the first conversion")

    def test_convert_writes_only_into_out_dir(self, case: Case, conformance_kit: Kit) -> None:
        if writes := conformance_kit.artifact(case, "second").writes:
            shown = ", ".join(writes[:5]) + (f" and {len(writes) - 5} more" if len(writes) > 5 else "")
            raise RuleBroken("convert-writes-only-out_dir", f"convert() wrote {shown} outside out_dir")

    def _same_as_first(self, case: Case, kit: Kit, session: Session, rule: str, what: str) -> None:
        """`session`'s outputs on the large batch (max_batch: a compiler has compiled for it) are the first
        load's."""
        model = kit.model(case.framework, case.model)
        allowed = bounds(self._tolerance(case.precision), model.large_reference)
        first = kit.run(kit.loaded(case).session, model.large, model.large_reference, allowed)
        again = kit.run(session, model.large, model.large_reference, allowed)
        check_close(again, first, bounds(REPEAT, model.large_reference), rule, what)
