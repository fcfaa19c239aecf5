"""The rounds scheduler (bench_matrix.measure.schedule) on fake sessions that run on a simulated machine
(tests/rounds_sim.py): orders, a cell's processes, stopping, lost sessions, disturbed windows (groups by
memory: tests/test_schedule_groups.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bench_matrix.measure.rounds import p50_interval
from bench_matrix.measure.schedule import LATENCY, Timed, Window, narrow, paired
from rounds_sim import NEVER_NARROW, FakeSession, Machine, cells, round_keys, rounds_on


# --- the scheduler ------------------------------------------------------------------------------------------


def test_every_round_visits_every_cell_once_in_a_fresh_random_order():
    machine = Machine(seed=0)
    names = ["a", "b", "c", "d", "e"]
    sessions = cells(machine, names, noise=0.3, kinds=(LATENCY, "throughput"))
    timed = {name: Timed() for name in names}
    rounds = rounds_on(machine, max_rounds=10, target=NEVER_NARROW, budget_s=1e9)
    assert rounds.run(sessions, timed, None, budget_s=1e9) == "rounds"
    assert len(rounds.orders) == 10 and rounds.number == 10
    assert all(sorted(order) == names for order in rounds.orders)  # each a permutation of the cells
    assert len(set(rounds.orders)) >= 5  # fresh orders (10 draws out of 120: ~10 distinct), not one reused
    visited = [cell for cell, kind, _ in machine.log if kind == LATENCY]
    assert [tuple(visited[i:i + 5]) for i in range(0, 50, 5)] == rounds.orders  # the order recorded is run
    assert [kind for _, kind, _ in machine.log] == [LATENCY, "throughput"] * 50  # a cell's kinds back to back
    for name in names:
        slots = {(r, 0) for r in range(10)}
        assert set(timed[name].kept[LATENCY]) == set(timed[name].kept["throughput"]) == slots
        assert sessions[name][0].windows == 20


def test_every_round_times_every_process_of_every_cell_once():
    machine = Machine(seed=0)
    sessions = cells(machine, ["base", "x", "y"], processes=2, noise=0.3)
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, max_rounds=6, target=NEVER_NARROW)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert all(sorted(order) == ["base", "base", "x", "x", "y", "y"] for order in rounds.orders)
    assert len({order for order in rounds.orders}) >= 3  # the processes of a cell are shuffled with the rest
    for name in sessions:
        assert set(timed[name].kept[LATENCY]) == {(r, j) for r in range(6) for j in (0, 1)}
        assert [session.windows for session in sessions[name]] == [6, 6] and timed[name].rounds() == 6


def test_the_baseline_is_visited_the_square_root_of_its_cells_times_a_round_its_repeats_latency_only():
    machine = Machine(seed=3)
    names = ["base", *(f"c{i}" for i in range(9))]
    sessions = cells(machine, names, processes=2, noise=0.3, calls=4, kinds=(LATENCY, "throughput"))
    timed = {name: Timed() for name in names}
    rounds = rounds_on(machine, max_rounds=4, target=NEVER_NARROW)
    assert rounds.visits(sessions, "base") == {"base": 3, **{name: 1 for name in names[1:]}}  # √9
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert all(sorted(order) == sorted(["base"] * 6 + [c for c in names[1:] for _ in "12"])
               for order in rounds.orders)
    assert len({order.index("base") for order in rounds.orders}) > 1  # its visits shuffled with the rest
    logged = [(cell, kind) for cell, kind, _ in machine.log]
    assert logged.count(("base", LATENCY)) == 24 and logged.count(("base", "throughput")) == 8
    assert logged.count(("c0", LATENCY)) == logged.count(("c0", "throughput")) == 8
    assert set(timed["base"].kept[LATENCY]) == {(r, j) for r in range(4) for j in (0, 1)}
    assert {len(w.durations_ms) for w in timed["base"].kept[LATENCY].values()} == {12}  # 3 visits' calls
    assert timed["base"].count(LATENCY) == (24, 0) and timed["c0"].count("throughput") == (8, 0)
    assert timed["base"].visits() == 3.0 and timed["c0"].visits() == timed["c0"].visits("throughput") == 1.0


def test_a_cell_paired_against_another_than_the_baseline_is_its_reference_alone():
    machine = Machine(seed=1)
    sessions = cells(machine, ["base", "a", "b", "c", "x@base", "x@new"])
    rounds = rounds_on(machine, references={"x@new": "x@base"})
    assert rounds.visits(sessions, "base") == {"base": 2, "a": 1, "b": 1, "c": 1, "x@base": 1, "x@new": 1}
    fewer = {key: sessions[key] for key in ("base", "a", "x@base", "x@new")}
    assert rounds.visits(fewer, "base")["base"] == 1  # √2, rounded
    without = {key: sessions[key] for key in ("a", "b", "c", "x@base")}
    assert rounds.visits(without, "base") == dict.fromkeys(without, 1)  # the baseline gone: nothing to repeat


def test_a_lost_process_fails_its_cell_and_its_other_process_is_not_timed_again():
    machine = Machine(seed=1)
    sessions = cells(machine, ["base", "x"], processes=2, noise=0.3)
    sessions["x"][1].crash_at = 2
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, max_rounds=6, target=NEVER_NARROW)
    rounds.run(sessions, timed, "base", budget_s=1e9)
    assert timed["x"].failed == "worker exited with signal 9"
    assert {0, 1} <= round_keys(timed["x"]) <= {0, 1, 2}  # its first process may have had round 2's window
    assert sessions["x"][0].windows <= 3 and all("x" not in order for order in rounds.orders[3:])
    assert timed["base"].failed is None and round_keys(timed["base"]) == set(range(6))


def test_the_rounds_order_comes_from_the_rng_given():
    def orders(seed: int) -> list[tuple[str, ...]]:
        machine = Machine(seed=0)
        rounds = rounds_on(machine, seed=seed, max_rounds=6, target=NEVER_NARROW)
        rounds.run(cells(machine, list("abcd")), {name: Timed() for name in "abcd"}, None, budget_s=1e9)
        return rounds.orders

    assert orders(7) == orders(7) and orders(7) != orders(8)


def test_quiet_cells_stop_on_width_right_after_min_rounds():
    machine = Machine(seed=1)
    sessions = cells(machine, ["base", "x", "y"], noise=0.001)
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "width"
    assert len(rounds.orders) == 5
    assert narrow(timed["x"], timed["base"], rounds.settings)
    assert paired(timed["base"], timed["x"]).half_width < 0.002


def test_quiet_cells_without_a_baseline_also_wait_for_min_rounds():
    machine = Machine(seed=1)
    rounds = rounds_on(machine, min_rounds=4, target=0.02)
    assert rounds.run(cells(machine, ["x", "y"]), {"x": Timed(), "y": Timed()}, None, budget_s=1e9) == "width"
    assert len(rounds.orders) == 4


def test_a_narrow_cell_leaves_the_rounds_and_the_rest_go_on_with_the_baseline():
    machine = Machine(seed=1)
    sessions = cells(machine, ["base", "x"], noise=0.001)
    sessions["y"] = [FakeSession(machine, "y", noise=0.5)]
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, max_rounds=12, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert all(sorted(order) == ["base", "x", "y"] for order in rounds.orders[:5])
    assert all(sorted(order) == ["base", "y"] for order in rounds.orders[5:]) and len(rounds.orders) == 12
    assert timed["x"].stop == "width" and round_keys(timed["x"]) == set(range(5))
    assert timed["y"].stop == "" and round_keys(timed["base"]) == round_keys(timed["y"]) == set(range(12))


def test_a_cell_stays_in_the_rounds_while_another_is_paired_against_it():
    machine = Machine(seed=1)
    sessions = cells(machine, ["base", "x@base", "y"], noise=0.001)
    sessions["x@new"] = [FakeSession(machine, "x@new", noise=0.5)]
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, max_rounds=9, target=0.02, references={"x@new": "x@base"})
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert all(sorted(order) == ["base", "x@base", "x@new"] for order in rounds.orders[5:])
    assert timed["y"].stop == "width" and timed["x@base"].stop == ""
    assert narrow(timed["x@base"], timed["base"], rounds.settings)  # narrow, yet kept for x@new's pairs


def test_each_session_times_its_own_kinds():
    machine = Machine(seed=1)
    sessions = {"x": [FakeSession(machine, "x", kinds=(LATENCY, "throughput"))],
                "y": [FakeSession(machine, "y")]}
    timed = {"x": Timed(), "y": Timed()}
    rounds_on(machine, max_rounds=3, target=NEVER_NARROW).run(sessions, timed, None, budget_s=1e9)
    assert sorted(timed["x"].kept) == [LATENCY, "throughput"] and list(timed["y"].kept) == [LATENCY]
    assert [kind for cell, kind, _ in machine.log if cell == "x"] == [LATENCY, "throughput"] * 3


def test_noisy_cells_stop_on_the_budget_of_the_fake_clock():
    machine = Machine(seed=2, step_s=0.0625)  # every window takes 1/16 s of simulated time
    sessions = cells(machine, ["base", "x", "y"], noise=0.5, calls=5)
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02, budget_s=1e9)
    assert rounds.run(sessions, timed, "base", budget_s=3.0) == "budget"
    assert len(rounds.orders) == 16  # 3 windows = 0.1875 s a round: 15 rounds make 2.81 s, 16 make 3.0 s
    assert machine.now == 3.0
    assert p50_interval(timed["x"].series(LATENCY)).half_width > 0.02  # the reason they were not narrow


def test_the_budget_leaves_at_least_two_rounds():
    machine = Machine(seed=3, step_s=1.0)
    sessions = cells(machine, ["base", "x"], noise=0.5)
    rounds = rounds_on(machine, target=NEVER_NARROW)
    assert rounds.run(sessions, {name: Timed() for name in sessions}, "base", budget_s=0.01) == "budget"
    assert len(rounds.orders) == 2


def test_noisy_cells_stop_on_max_rounds():
    machine = Machine(seed=4)
    sessions = cells(machine, ["base", "x"], noise=0.5)
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, max_rounds=7, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert len(rounds.orders) == 7 and round_keys(timed["x"]) == set(range(7))


def test_a_lost_session_fails_only_its_cell():
    machine = Machine(seed=5)
    sessions = cells(machine, ["base", "a", "b"], noise=0.3)
    sessions["lost"] = [FakeSession(machine, "lost", noise=0.3, crash_at=3)]  # its window in round 3
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, max_rounds=8, target=NEVER_NARROW)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert timed["lost"].failed == "worker exited with signal 9"
    assert round_keys(timed["lost"]) == {0, 1, 2} and sessions["lost"][0].windows == 4  # not asked again
    assert ["lost" in order for order in rounds.orders] == [True] * 4 + [False] * 4
    for name in ["base", "a", "b"]:
        assert timed[name].failed is None and round_keys(timed[name]) == set(range(8))
    assert paired(timed["base"], timed["a"]).rounds == 8


def test_rounds_end_failed_when_every_session_is_lost():
    machine = Machine(seed=6)
    sessions = {name: [FakeSession(machine, name, crash_at=1)] for name in ["base", "x"]}
    timed = {name: Timed() for name in sessions}
    assert rounds_on(machine, target=NEVER_NARROW).run(sessions, timed, "base", budget_s=1e9) == "failed"
    assert all(t.failed and round_keys(t) == {0} for t in timed.values())


# --- disturbed windows --------------------------------------------------------------------------------------


def window(ms: float, disturbed: str | None = None, kind: str = LATENCY) -> Window:
    return Window(kind, durations_ms=np.full(5, ms), disturbed=disturbed)


STEAL = "CPU steal 9% (limit 3%)"


def test_disturbed_windows_are_kept_apart_while_two_clean_rounds_exist():
    timed = Timed()
    for number in range(6):
        disturbed = number in (1, 4)
        timed.add((number, 0), window(40.0 if disturbed else 10.0 + number, STEAL if disturbed else None))
        timed.add((number, 0), window(3.0, kind="throughput"))
    assert set(timed.dropped[LATENCY]) == {(1, 0), (4, 0)} and round_keys(timed) == set(range(6))
    assert timed.dropped[LATENCY][1, 0].disturbed == STEAL and "throughput" not in timed.dropped
    assert list(timed.series(LATENCY)) == [(0, 0), (2, 0), (3, 0), (5, 0)]
    assert timed.series(LATENCY) == timed.series(LATENCY, clean=True)
    assert p50_interval(timed.series(LATENCY)).value == 12.5  # median of 10, 12, 13, 15: the 40s are left out
    assert timed.count(LATENCY) == (6, 2) and timed.count("throughput") == (6, 0)  # 2 of the 12 windows


def test_series_falls_back_to_every_window_when_fewer_than_two_are_clean():
    timed = Timed()
    for number in range(4):
        timed.add((number, 0), window(10.0 + number, None if number == 2 else STEAL))
    assert list(timed.series(LATENCY)) == [(r, 0) for r in range(4)]  # all of them, in round order
    assert list(timed.series(LATENCY, clean=True)) == [(2, 0)]
    assert timed.count(LATENCY) == (4, 3)
    assert Timed().series(LATENCY) == {} and Timed().count(LATENCY) == (0, 0)


def test_speed_ups_pair_clean_rounds_or_every_round_when_fewer_than_two_are_clean_in_both():
    base, cell = Timed(), Timed()
    for number in range(6):  # clean in base in rounds 0-2, in the cell in 3-5: no two rounds clean in both
        base.add((number, 0), window(20.0 * (1 + number), None if number < 3 else STEAL))
        cell.add((number, 0), window(10.0 * (1 + number), None if number >= 3 else STEAL))
    found = paired(base, cell)
    assert found is not None and found.rounds == 6 and found.value == pytest.approx(2.0)
    assert paired(base, cell, clean=True) is None  # what decides stopping counts clean rounds only
    cell.add((6, 0), window(35.0))
    base.add((6, 0), window(140.0))
    cell.add((7, 0), window(40.0))
    base.add((7, 0), window(160.0))
    assert paired(base, cell).rounds == 2 and paired(base, cell).value == pytest.approx(4.0)


def test_disturbed_rounds_do_not_count_towards_stopping():
    machine = Machine(seed=13)
    sessions = cells(machine, ["base"], noise=0.001)
    sessions["x"] = [FakeSession(machine, "x", noise=0.001, disturbed_at=(1, 3))]
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "width"
    assert len(rounds.orders) == 7  # x's 5th clean round is round 6
    assert set(timed["x"].dropped[LATENCY]) == {(1, 0), (3, 0)}
    assert timed["x"].count(LATENCY) == (7, 2)

    machine = Machine(seed=15)  # pairs need 5 rounds clean in both: base's 0 and 2 are out, x's 1 and 3
    sessions = {"base": [FakeSession(machine, "base", disturbed_at=(0, 2))],
                "x": [FakeSession(machine, "x", disturbed_at=(1, 3))]}
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "width"
    assert len(rounds.orders) == 9 and paired(timed["base"], timed["x"], clean=True).rounds == 5

    machine = Machine(seed=14)
    always = {"x": [FakeSession(machine, "x", noise=0.001, disturbed_at=tuple(range(100)))]}
    rounds = rounds_on(machine, min_rounds=5, max_rounds=12, target=0.02)
    assert rounds.run(always, {"x": Timed()}, None, budget_s=1e9) == "rounds"
