"""The rounds scheduler's groups (bench_matrix.measure.schedule.measure_groups) on fake sessions that run on
a simulated machine (tests/rounds_sim.py): cells grouped by resident memory (a cell's processes together), the
baseline in every group, sessions that fail to open or are lost, each group's share of the budget and of the
timing lock."""

from __future__ import annotations

import random
from contextlib import contextmanager

from bench_matrix.measure.schedule import Rounds, RoundsSettings, SessionLost, measure_groups, paired
from rounds_sim import NEVER_NARROW, FakeSession, Machine, round_keys, rounds_on


class Opener:
    """open_session / close for measure_groups: records what is alive, the peak resident memory, the order
    sessions open and close in; opening a name in `fail_open` raises SessionLost."""

    def __init__(self, machine: Machine, fail_open: tuple[str, ...] = (), **session):
        self.machine, self.fail_open, self.session = machine, fail_open, session
        self.alive: dict[str, FakeSession] = {}
        self.opened: list[str] = []
        self.closed: list[str] = []
        self.peak_mb = 0.0
        self.closed_at: dict[str, int] = {}  # len(machine.log) when each session closed

    def open(self, name: str) -> list[FakeSession]:
        if name in self.fail_open:
            raise SessionLost(f"{name}: model failed to load")
        assert name not in self.alive
        self.opened.append(name)
        self.alive[name] = [FakeSession(self.machine, name, **self.session)]
        self.peak_mb = max(self.peak_mb, sum(s.rss_mb for cell in self.alive.values() for s in cell))
        return self.alive[name]

    def close(self, name: str, session: list[FakeSession]) -> None:
        assert self.alive.pop(name) is session
        self.closed.append(name)
        self.closed_at[name] = len(self.machine.log)


def test_groups_fit_memory_with_the_baseline_in_every_group():
    machine = Machine(seed=7)
    opener = Opener(machine, noise=0.001)
    keys = ["base", "c1", "c2", "c3", "c4", "c5"]
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(keys, "base", opener.open, opener.close, memory_mb=300, rounds=rounds)
    # groups {base, c1, c2}, {base, c3, c4}, {base, c5}: 3 quiet rounds each, numbered on across groups
    assert rounds.number == 9
    assert round_keys(timed["base"]) == set(range(9))
    assert round_keys(timed["c1"]) == round_keys(timed["c2"]) == {0, 1, 2}
    assert round_keys(timed["c3"]) == round_keys(timed["c4"]) == {3, 4, 5}
    assert round_keys(timed["c5"]) == {6, 7, 8}
    assert [sorted(order) for order in rounds.orders[::3]] == [["base", "c1", "c2"], ["base", "c3", "c4"],
                                                                ["base", "c5"]]
    assert opener.opened == keys and opener.closed == ["c1", "c2", "c3", "c4", "c5", "base"]
    assert opener.peak_mb == 300 and not opener.alive
    for key in keys:  # closed once its rounds were done, and never timed after
        windows = [i for i, (cell, _, _) in enumerate(machine.log) if cell == key]
        assert windows[-1] < opener.closed_at[key]
    assert opener.closed_at["c2"] < min(i for i, (cell, _, _) in enumerate(machine.log) if cell == "c3")
    assert all(t.failed is None and t.stop == "width" for t in timed.values())
    assert all(paired(timed["base"], timed[key]).rounds == 3 for key in keys[1:])  # paired within its group


def test_a_session_that_fails_to_open_fails_only_its_cell():
    machine = Machine(seed=8)
    opener = Opener(machine, fail_open=("c3",), noise=0.001)
    keys = ["base", "c1", "c2", "c3", "c4", "c5"]
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(keys, "base", opener.open, opener.close, memory_mb=300, rounds=rounds)
    assert timed["c3"].failed == "c3: model failed to load" and round_keys(timed["c3"]) == set()
    assert "c3" not in opener.opened and "c3" not in opener.closed
    assert opener.closed == ["c1", "c2", "c4", "c5", "base"] and not opener.alive
    assert round_keys(timed["c4"]) == round_keys(timed["c5"]) == {3, 4, 5}  # c4 takes c3's place
    assert all(timed[key].failed is None for key in keys if key != "c3")


def test_a_baseline_whose_cells_all_fail_to_open_is_timed_alone():
    machine = Machine(seed=10)
    opener = Opener(machine, fail_open=("c1", "c2"), noise=0.001)
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(["base", "c1", "c2"], "base", opener.open, opener.close, memory_mb=300,
                           rounds=rounds)
    assert round_keys(timed["base"]) == {0, 1, 2} and timed["base"].stop == "width"
    assert opener.closed == ["base"] and timed["c1"].failed and timed["c2"].failed


def test_a_group_whose_cells_all_fail_to_open_spends_no_rounds():
    machine = Machine(seed=11)
    opener = Opener(machine, fail_open=("c1", "c2"), noise=0.001)
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(["base", "c1", "c2", "c3"], "base", opener.open, opener.close, memory_mb=200,
                           rounds=rounds)
    assert rounds.number == 3 and [sorted(o) for o in rounds.orders] == [["base", "c3"]] * 3
    assert round_keys(timed["c3"]) == round_keys(timed["base"]) == {0, 1, 2}


def test_a_baseline_that_fails_to_open_leaves_the_cells_grouped_by_memory_alone():
    machine = Machine(seed=9)
    opener = Opener(machine, fail_open=("base",), noise=0.001)
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(["base", "c1", "c2", "c3"], "base", opener.open, opener.close, memory_mb=200,
                           rounds=rounds)
    assert timed["base"].failed == "base: model failed to load"
    assert [sorted(order) for order in rounds.orders[::3]] == [["c1", "c2"], ["c3"]]
    assert opener.closed == ["c1", "c2", "c3"] and opener.peak_mb == 200


def test_each_group_gets_its_share_of_the_budget():
    machine = Machine(seed=10, step_s=0.0625)
    opener = Opener(machine, noise=0.5, calls=5)
    rounds = rounds_on(machine, target=NEVER_NARROW, budget_s=6.0)  # 2 s for each of the 3 cells
    timed = measure_groups(["base", "c1", "c2", "c3"], "base", opener.open, opener.close, memory_mb=300,
                           rounds=rounds)
    # {base, c1, c2}: 4 s at 0.1875 s a round -> 22 rounds; {base, c3}: 2 s at 0.125 s a round -> 16 rounds
    assert len(round_keys(timed["c1"])) == 22 and len(round_keys(timed["c3"])) == 16
    assert len(round_keys(timed["base"])) == 38
    assert all(t.stop == "budget" for t in timed.values())


def test_a_session_lost_in_its_rounds_is_closed_once_and_the_rest_go_on():
    machine = Machine(seed=11)
    opener = Opener(machine, noise=0.001)
    original_open = opener.open

    def open_with_a_crash(name: str) -> list[FakeSession]:
        session = original_open(name)
        session[0].crash_at = 1 if name == "c2" else None
        return session

    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(["base", "c1", "c2", "c3"], "base", open_with_a_crash, opener.close, memory_mb=300,
                           rounds=rounds)
    assert timed["c2"].failed and round_keys(timed["c2"]) == {0}
    assert opener.closed == ["c1", "c2", "c3", "base"] and not opener.alive
    assert round_keys(timed["c1"]) == {0, 1, 2} and round_keys(timed["base"]) == set(range(6))


def test_rounds_are_timed_under_hold_and_announced_as_they_begin():
    machine = Machine(seed=12)
    opener = Opener(machine, noise=0.001)
    held: list[tuple[int, int]] = []  # (len(machine.log) when taken, when released), one per group
    begun: list[tuple[int, int]] = []  # (round number, len(machine.log) when it began)

    @contextmanager
    def timing_lock():
        taken = len(machine.log)
        yield
        held.append((taken, len(machine.log)))

    rounds = Rounds(RoundsSettings(min_rounds=3, target=0.02), rng=random.Random(1), clock=machine.clock,
                    hold=timing_lock, on_round=lambda number: begun.append((number, len(machine.log))))
    measure_groups(["base", "c1", "c2", "c3", "c4"], "base", opener.open, opener.close, memory_mb=300,
                   rounds=rounds)
    assert held == [(0, 9), (9, 18)]  # two groups of 3 cells, 3 rounds each: every window inside a hold
    assert begun == [(number, 3 * number) for number in range(6)]


def test_groups_never_hold_more_resident_memory_than_the_budget():
    machine = Machine(seed=12)
    opener = Opener(machine, noise=0.001)
    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    measure_groups(["base", "c1", "c2", "c3"], "base", opener.open, opener.close, memory_mb=250,
                   rounds=rounds)
    assert opener.peak_mb <= 250  # base + 1 cell (200 MB) fit; base + 2 cells (300 MB) do not


def test_a_cells_processes_count_together_against_the_memory_budget():
    machine = Machine(seed=2)
    opened: list[str] = []

    def open_two(name: str) -> list[FakeSession]:
        opened.append(name)
        return [FakeSession(machine, name, noise=0.001, rss_mb=100.0) for _ in range(2)]

    rounds = rounds_on(machine, min_rounds=3, target=0.02)
    timed = measure_groups(["base", "c1", "c2", "c3"], "base", open_two, lambda name, cell: None,
                           memory_mb=400, rounds=rounds)
    assert [sorted(set(order)) for order in rounds.orders[::3]] == [["base", "c1"], ["base", "c2"],
                                                                     ["base", "c3"]]  # 2 cells of 200 MB each
    assert all(t.failed is None for t in timed.values())
