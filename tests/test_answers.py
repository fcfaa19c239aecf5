"""The rounds spend their budget on the answers still open (bench_matrix/executors/answers.py): simulated
sessions on a simulated clock (tests/rounds_sim.py), judged against real requirements. Nothing here reads the
real clock."""

from __future__ import annotations

import random
from typing import Any

from bench_matrix.executors.answers import OpenAnswers
from bench_matrix.matrix.requirements import Requirements
from bench_matrix.measure.interference import LIMITS
from bench_matrix.measure.schedule import LOOSE, Rounds, RoundsSettings, Timed
from bench_matrix.scenarios.timed import figures
from rounds_sim import Machine, cells

SETTINGS = RoundsSettings(min_rounds=5, max_rounds=60, budget_s=1e9)


def run(machine: Machine, sessions: dict, requirements: dict[str, Any], evaluated: dict[str, dict],
        settings: RoundsSettings = SETTINGS) -> tuple[dict[str, Timed], str]:
    """The rounds of `sessions` (baseline "base") serving `requirements`; each cell's Timed and the stop."""
    answers = OpenAnswers(Requirements.from_data(requirements), "regression", "base", settings, evaluated)
    rounds = Rounds(settings, random.Random(1), clock=machine.clock, answers=answers)
    timed = {key: Timed() for key in sessions}
    stop = rounds.run(sessions, timed, "base", settings.budget_s)
    return timed, stop


def accurate(*keys: str, mse: float = 0.010) -> dict[str, dict]:
    return {key: {"mse": mse} for key in keys}


def test_a_cell_far_from_every_limit_and_behind_the_leaders_leaves_early_and_the_leaders_keep_the_budget():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0), **cells(machine, ["lead", "twin"], base_ms=4.0),
                **cells(machine, ["far"], base_ms=9.0)}
    evaluated = accurate("base", "lead", "twin", "far")
    timed, stop = run(machine, sessions, {"p50_ms": 50, "max_drop": "5%"}, evaluated)
    assert timed["far"].stop == "width" and timed["far"].rounds() == SETTINGS.min_rounds
    assert timed["far"].open is None
    assert stop == "rounds" and timed["lead"].rounds() == timed["twin"].rounds() == SETTINGS.max_rounds
    assert timed["lead"].open.startswith("leads by p50; not yet told apart from")
    assert timed["twin"].open.startswith("leads by p50") or "the leader" in timed["twin"].open


def test_a_leader_told_apart_from_its_runner_up_leaves_with_the_rest():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0), **cells(machine, ["lead"], base_ms=4.0),
                **cells(machine, ["next"], base_ms=6.0)}
    timed, stop = run(machine, sessions, {}, accurate("base", "lead", "next"))
    assert stop == "width" and all(t.rounds() == SETTINGS.min_rounds for t in timed.values())
    assert all(t.open is None for t in timed.values())


def test_an_uncertain_cell_keeps_the_budget_until_it_ends():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0), **cells(machine, ["edge"], base_ms=7.0),
                **cells(machine, ["fast"], base_ms=3.0)}
    # the limit at the edge cell's p50 itself: its interval straddles it however narrow it gets
    edge_p50 = 7.0
    timed, stop = run(machine, sessions, {"p50_ms": edge_p50}, accurate("base", "edge", "fast"),
                      RoundsSettings(min_rounds=5, max_rounds=40, budget_s=1e9))
    assert timed["fast"].stop == "width" and timed["fast"].rounds() == 5
    assert stop == "rounds" and timed["edge"].rounds() == 40
    assert timed["edge"].open.startswith("uncertain: p50_ms")


def test_a_cell_that_fails_its_accuracy_cannot_lead_and_leaves_early_however_fast():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0), **cells(machine, ["wrong", "right"], base_ms=4.0)}
    evaluated = {**accurate("base", "right"), **accurate("wrong", mse=0.5)}
    timed, stop = run(machine, sessions, {"max_drop": "5%"}, evaluated)
    assert timed["wrong"].stop == "width" and timed["wrong"].rounds() == SETTINGS.min_rounds
    assert timed["right"].open is None  # the only passing cell besides the slower baseline: told apart


def test_without_requirements_the_objectives_leaders_get_the_budget():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0), **cells(machine, ["a", "b"], base_ms=4.0),
                **cells(machine, ["slow"], base_ms=20.0)}
    timed, _ = run(machine, sessions, {}, accurate("base", "a", "b", "slow"))
    assert timed["slow"].rounds() == SETTINGS.min_rounds
    assert timed["a"].rounds() == timed["b"].rounds() == SETTINGS.max_rounds


def test_a_scenarios_requirement_is_left_to_the_report():
    answers = OpenAnswers(Requirements.from_data({"p50_ms": 5, "closed_loop": {"completed_pct": 90}}),
                          "regression", None, SETTINGS, {})
    assert [limit.key for limit in answers.requirements.limits] == ["p50_ms"]


def test_the_record_says_what_was_open_and_marks_a_width_only_where_the_target_was_asked():
    machine = Machine(0)
    sessions = {**cells(machine, ["base"], base_ms=10.0),
                **cells(machine, ["a", "b"], base_ms=4.0, noise=0.2)}
    timed, _ = run(machine, sessions, {}, accurate("base", "a", "b"),
                   RoundsSettings(min_rounds=5, max_rounds=8, budget_s=1e9, target=0.001))
    loose = figures(timed["a"], timed["base"], RoundsSettings(target=LOOSE), LIMITS, {})
    assert loose["rounds"]["open"] == timed["a"].open and loose["rounds"]["asked"] is False
    assert loose["rounds"]["window_spread"] > 0
    assert loose["interference"]["phases"]["latency"]["wide"] is None
    asked = figures(timed["a"], timed["base"], RoundsSettings(target=0.001, asked=True), LIMITS, {})
    assert asked["interference"]["phases"]["latency"]["wide"].startswith("known to ±")
