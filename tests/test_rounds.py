"""Interleaved timing rounds: the rounds scheduler (bench_matrix.measure.schedule) on fake sessions that run
on a simulated machine (its own clock, a speed that drifts, seeded noise), and the statistics over rounds
(bench_matrix.measure.rounds). Nothing here reads the real clock."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np
import pytest

from bench_matrix.measure.rounds import (Interval, log_interval, medians_by_round, p50_interval,
                                         rate_interval, speedup, t95)
from bench_matrix.measure.schedule import (LATENCY, Rounds, RoundsSettings, SessionLost, Timed, Window,
                                           measure_groups, narrow, paired)
from bench_matrix.measure.stats import median_interval

NEVER_NARROW = 1e-9  # a target no interval reaches: rounds then end on the budget or on max_rounds


class Machine:
    """A simulated machine: a clock in seconds that every window advances (by the window's durations, or by
    `step_s` each), a speed factor `drift(t)` (1.0: nominal), seeded noise, and a log of the windows run."""

    def __init__(self, seed: int, drift: Callable[[float], float] = lambda t: 1.0,
                 step_s: float | None = None):
        self.now, self.drift, self.step_s = 0.0, drift, step_s
        self.rng = np.random.default_rng(seed)
        self.log: list[tuple[str, str, float]] = []  # (cell, kind, time the window started)

    def clock(self) -> float:
        return self.now

    def run(self, cell: str, kind: str, base_ms: float, calls: int, noise: float) -> np.ndarray:
        """One window's durations: the drift at its start times lognormal noise of sigma `noise`."""
        self.log.append((cell, kind, self.now))
        durations = base_ms * self.drift(self.now) * np.exp(self.rng.normal(0.0, noise, calls))
        self.now += self.step_s if self.step_s is not None else float(durations.sum()) / 1000
        return durations


class FakeSession:
    """A loaded cell on `machine` timing `kinds`: `calls` timed calls of `base_ms` per window; SessionLost on
    its window number `crash_at` (0-based); windows numbered in `disturbed_at` come back disturbed."""

    def __init__(self, machine: Machine, name: str, base_ms: float = 10.0, noise: float = 0.001,
                 calls: int = 20, rss_mb: float = 100.0, crash_at: int | None = None,
                 disturbed_at: tuple[int, ...] = (), kinds: tuple[str, ...] = (LATENCY,)):
        self.machine, self.name, self.base_ms, self.noise, self.calls = machine, name, base_ms, noise, calls
        self.kinds = kinds
        self.rss_mb, self.crash_at, self.disturbed_at = rss_mb, crash_at, disturbed_at
        self.windows = 0  # windows asked for, the crashing one included

    def window(self, kind: str) -> Window:
        number, self.windows = self.windows, self.windows + 1
        if number == self.crash_at:
            raise SessionLost("worker exited with signal 9")
        durations = self.machine.run(self.name, kind, self.base_ms, self.calls, self.noise)
        disturbed = "CPU steal 9% (limit 3%)" if number in self.disturbed_at else None
        return Window(kind, durations_ms=durations, disturbed=disturbed)


def rounds_on(machine: Machine, seed: int = 1, **settings) -> Rounds:
    return Rounds(RoundsSettings(**settings), rng=random.Random(seed), clock=machine.clock)


def cells(machine: Machine, names: list[str], **session) -> dict[str, FakeSession]:
    return {name: FakeSession(machine, name, **session) for name in names}


def round_keys(timed: Timed, kind: str = LATENCY) -> set[int]:
    return set(timed.kept.get(kind, {})) | set(timed.dropped.get(kind, {}))


# --- the scheduler ------------------------------------------------------------------------------------------


def test_every_round_visits_every_cell_once_in_a_fresh_random_order():
    machine = Machine(seed=0)
    names = ["a", "b", "c", "d", "e"]
    sessions = cells(machine, names, noise=0.3, kinds=(LATENCY, "throughput"))
    timed = {name: Timed() for name in names}
    rounds = rounds_on(machine, max_rounds=10, target=NEVER_NARROW, budget_s=1e9)
    assert rounds.run(sessions, timed, "a", budget_s=1e9) == "rounds"
    assert len(rounds.orders) == 10 and rounds.number == 10
    assert all(sorted(order) == names for order in rounds.orders)  # each a permutation of the cells
    assert len(set(rounds.orders)) >= 5  # fresh orders (10 draws out of 120: ~10 distinct), not one reused
    visited = [cell for cell, kind, _ in machine.log if kind == LATENCY]
    assert [tuple(visited[i:i + 5]) for i in range(0, 50, 5)] == rounds.orders  # the order recorded is run
    assert [kind for _, kind, _ in machine.log] == [LATENCY, "throughput"] * 50  # a cell's kinds back to back
    for name in names:
        assert set(timed[name].kept[LATENCY]) == set(timed[name].kept["throughput"]) == set(range(10))
        assert sessions[name].windows == 20


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


def test_each_session_times_its_own_kinds():
    machine = Machine(seed=1)
    sessions = {"x": FakeSession(machine, "x", kinds=(LATENCY, "throughput")), "y": FakeSession(machine, "y")}
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
    sessions["lost"] = FakeSession(machine, "lost", noise=0.3, crash_at=3)  # its window in round 3
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, max_rounds=8, target=NEVER_NARROW)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "rounds"
    assert timed["lost"].failed == "worker exited with signal 9"
    assert round_keys(timed["lost"]) == {0, 1, 2} and sessions["lost"].windows == 4  # not asked again
    assert ["lost" in order for order in rounds.orders] == [True] * 4 + [False] * 4
    for name in ["base", "a", "b"]:
        assert timed[name].failed is None and round_keys(timed[name]) == set(range(8))
    assert paired(timed["base"], timed["a"]).rounds == 8


def test_rounds_end_failed_when_every_session_is_lost():
    machine = Machine(seed=6)
    sessions = {name: FakeSession(machine, name, crash_at=1) for name in ["base", "x"]}
    timed = {name: Timed() for name in sessions}
    assert rounds_on(machine, target=NEVER_NARROW).run(sessions, timed, "base", budget_s=1e9) == "failed"
    assert all(t.failed and round_keys(t) == {0} for t in timed.values())


# --- groups by memory ---------------------------------------------------------------------------------------


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

    def open(self, name: str) -> FakeSession:
        if name in self.fail_open:
            raise SessionLost(f"{name}: model failed to load")
        assert name not in self.alive
        self.opened.append(name)
        self.alive[name] = FakeSession(self.machine, name, **self.session)
        self.peak_mb = max(self.peak_mb, sum(s.rss_mb for s in self.alive.values()))
        return self.alive[name]

    def close(self, name: str, session: FakeSession) -> None:
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

    def open_with_a_crash(name: str) -> FakeSession:
        session = original_open(name)
        session.crash_at = 1 if name == "c2" else None
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


# --- disturbed windows --------------------------------------------------------------------------------------


def window(ms: float, disturbed: str | None = None, kind: str = LATENCY) -> Window:
    return Window(kind, durations_ms=np.full(5, ms), disturbed=disturbed)


STEAL = "CPU steal 9% (limit 3%)"


def test_disturbed_windows_are_kept_apart_while_two_clean_rounds_exist():
    timed = Timed()
    for number in range(6):
        disturbed = number in (1, 4)
        timed.add(number, window(40.0 if disturbed else 10.0 + number, STEAL if disturbed else None))
        timed.add(number, window(3.0, kind="throughput"))
    assert set(timed.dropped[LATENCY]) == {1, 4} and set(timed.kept[LATENCY]) == {0, 2, 3, 5}
    assert timed.dropped[LATENCY][1].disturbed == STEAL and "throughput" not in timed.dropped
    assert list(timed.series(LATENCY)) == [0, 2, 3, 5]
    assert timed.series(LATENCY) == timed.series(LATENCY, clean=True)
    assert p50_interval(timed.series(LATENCY)).value == 12.5  # median of 10, 12, 13, 15: the 40s are left out
    assert timed.disturbed_share() == pytest.approx(2 / 12)  # 2 of the 12 windows, every kind counted


def test_series_falls_back_to_every_window_when_fewer_than_two_are_clean():
    timed = Timed()
    for number in range(4):
        timed.add(number, window(10.0 + number, None if number == 2 else STEAL))
    assert list(timed.series(LATENCY)) == [0, 1, 2, 3]  # all of them, in round order
    assert list(timed.series(LATENCY, clean=True)) == [2]
    assert timed.disturbed_share() == 0.75
    assert Timed().series(LATENCY) == {} and Timed().disturbed_share() == 0.0


def test_disturbed_rounds_do_not_count_towards_stopping():
    machine = Machine(seed=13)
    sessions = cells(machine, ["base"], noise=0.001)
    sessions["x"] = FakeSession(machine, "x", noise=0.001, disturbed_at=(1, 3))
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "width"
    assert len(rounds.orders) == 7  # x's 5th clean round is round 6
    assert set(timed["x"].dropped[LATENCY]) == {1, 3} and timed["x"].disturbed_share() == pytest.approx(2 / 7)

    machine = Machine(seed=15)  # pairs need 5 rounds clean in both: base's 0 and 2 are out, x's 1 and 3
    sessions = {"base": FakeSession(machine, "base", disturbed_at=(0, 2)),
                "x": FakeSession(machine, "x", disturbed_at=(1, 3))}
    timed = {name: Timed() for name in sessions}
    rounds = rounds_on(machine, min_rounds=5, target=0.02)
    assert rounds.run(sessions, timed, "base", budget_s=1e9) == "width"
    assert len(rounds.orders) == 9 and paired(timed["base"], timed["x"], clean=True).rounds == 5

    machine = Machine(seed=14)
    always = {"x": FakeSession(machine, "x", noise=0.001, disturbed_at=tuple(range(100)))}
    rounds = rounds_on(machine, min_rounds=5, max_rounds=12, target=0.02)
    assert rounds.run(always, {"x": Timed()}, None, budget_s=1e9) == "rounds"


# --- statistics under drift ---------------------------------------------------------------------------------

BASE_MS = 10.0


def drifting_runs(rng: np.random.Generator, runs: int, rounds: int, calls: int, drift_sigma: float,
                  noise_sigma: float, round_corr: float) -> np.ndarray:
    """Durations (runs, rounds, calls): log speed a stationary AR(1) over rounds (sd `drift_sigma`,
    correlation `round_corr` from one round to the next: it moves on the scale of a round, held through each
    window), times iid lognormal noise. The log of every sample is symmetric about log BASE_MS, so BASE_MS is
    the median of the process over any long run."""
    level = np.empty((runs, rounds))
    level[:, 0] = rng.normal(0.0, drift_sigma, runs)
    for r in range(1, rounds):
        fresh = rng.normal(0.0, drift_sigma * math.sqrt(1 - round_corr**2), runs)
        level[:, r] = round_corr * level[:, r - 1] + fresh
    return BASE_MS * np.exp(level[:, :, None] + rng.normal(0.0, noise_sigma, (runs, rounds, calls)))


def coverages(samples: np.ndarray) -> tuple[float, float]:
    """How often BASE_MS lies in the round-based p50 interval, and in the iid interval of pooled samples."""
    by_rounds = pooled = 0
    for run in samples:
        interval = p50_interval(dict(enumerate(run)))
        by_rounds += interval.low <= BASE_MS <= interval.high
        low, high = median_interval(run.ravel())
        pooled += low <= BASE_MS <= high
    return by_rounds / len(samples), pooled / len(samples)


def test_the_process_median_is_the_base_time():
    long_run = drifting_runs(np.random.default_rng(0), 1, 20_000, 50, 0.05, 0.03, 0.1)
    assert np.median(long_run) == pytest.approx(BASE_MS, rel=5e-4)


def test_round_intervals_cover_the_median_under_drift_where_pooled_iid_intervals_do_not():
    samples = drifting_runs(np.random.default_rng(6), 300, 20, 50, drift_sigma=0.05, noise_sigma=0.03,
                            round_corr=0.1)
    by_rounds, pooled = coverages(samples)
    assert by_rounds >= 0.85  # ~0.93 here (0.95 stated)
    assert pooled < 0.5  # ~0.27: 1000 samples look precise, but they come from 20 drifting levels
    widths = [p50_interval(dict(enumerate(run))).half_width for run in samples]
    assert 0.022 < float(np.median(widths)) < 0.05  # the drift widens it: 1.41 * 2.09 * 0.05 / sqrt(20) = 0.033


def test_a_reruns_p50_falls_in_the_stated_interval():
    """Two runs of the same drifting process: run 2's pooled p50 lies in run 1's interval about 95 % of the
    time (an interval of the first run's level alone would cover it about 83 %)."""
    first, second = np.split(drifting_runs(np.random.default_rng(8), 600, 12, 50, drift_sigma=0.03,
                                           noise_sigma=0.03, round_corr=0.1), 2)
    inside = [(i := p50_interval(dict(enumerate(a)))).low <= float(np.median(b)) <= i.high
              for a, b in zip(first, second)]
    assert 0.9 <= sum(inside) / len(inside) <= 0.99


def test_without_drift_both_intervals_cover_the_median():
    samples = drifting_runs(np.random.default_rng(7), 300, 20, 50, drift_sigma=0.0, noise_sigma=0.03,
                            round_corr=0.0)
    by_rounds, pooled = coverages(samples)
    assert by_rounds >= 0.88 and pooled >= 0.88
    assert float(np.median([p50_interval(dict(enumerate(run))).half_width for run in samples])) < 0.004


def test_paired_speedup_cancels_the_drift_both_cells_share():
    """Baseline and a cell twice as fast on one machine whose speed swings ±10 % slowly (a sine of 20 s
    period over 12 s of rounds, random phase): the paired interval is far narrower than the unpaired one
    and covers 2."""
    covered, paired_widths, unpaired_widths = 0, [], []
    for seed in range(40):
        phase = random.Random(seed).uniform(0, 2 * math.pi)
        swing = lambda t, phase=phase: math.exp(0.1 * math.sin(2 * math.pi * t / 20 + phase))  # noqa: E731
        machine = Machine(seed, drift=swing)
        sessions = {"base": FakeSession(machine, "base", base_ms=10.0, noise=0.03),
                    "fast": FakeSession(machine, "fast", base_ms=5.0, noise=0.03)}
        timed = {name: Timed() for name in sessions}
        rounds_on(machine, seed=seed, max_rounds=40, target=NEVER_NARROW).run(sessions, timed, "base", 1e9)
        ratio = paired(timed["base"], timed["fast"])
        assert ratio.rounds == 40
        covered += ratio.low <= 2.0 <= ratio.high
        paired_widths.append(ratio.half_width)
        halves = [p50_interval(timed[name].series(LATENCY)).half_width for name in sessions]
        unpaired_widths.append(math.hypot(*halves))
    assert covered / 40 >= 0.85
    assert float(np.median(paired_widths)) < float(np.median(unpaired_widths)) / 3
    assert max(paired_widths) < 0.01 < float(np.median(unpaired_widths))


# --- the statistics themselves ------------------------------------------------------------------------------


@pytest.mark.parametrize("df, quantile, rel", [(1, 12.706, 1e-4), (10, 2.228, 1e-4), (30, 2.042, 1e-4),
                                               (31, 2.0395, 3e-3), (60, 2.000, 3e-3), (120, 1.980, 3e-3),
                                               (10_000, 1.960, 3e-3)])
def test_t95_matches_student_quantiles(df, quantile, rel):
    assert t95(df) == pytest.approx(quantile, rel=rel)


def test_log_interval_is_a_t_interval_on_the_logs():
    interval = log_interval(2.0, [1.0, 2.0, 4.0])
    half = 4.303 * math.log(2) / math.sqrt(3)  # sd of (0, ln 2, 2 ln 2) is ln 2; df 2
    assert interval.low == pytest.approx(2.0 * math.exp(-half))
    assert interval.high == pytest.approx(2.0 * math.exp(half))
    assert interval.value == 2.0 and interval.rounds == 3
    assert interval.half_width == pytest.approx(math.exp(half) - 1)  # the upper side is the larger one


@pytest.mark.filterwarnings("ignore:divide by zero:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
@pytest.mark.parametrize("value, per_round", [(5.0, []), (5.0, [5.0]), (0.0, [1.0, 2.0]), (-1.0, [1.0, 2.0]),
                                              (5.0, [4.0, 0.0]), (5.0, [4.0, -6.0])])
def test_log_interval_needs_two_positive_rounds(value, per_round):
    assert log_interval(value, per_round) is None


def test_interval_half_width_is_the_larger_side_relative_to_the_value():
    assert Interval(10.0, 9.0, 10.5, 4).half_width == pytest.approx(0.1)
    assert Interval(10.0, 9.8, 10.3, 4).half_width == pytest.approx(0.03)
    assert Interval(10.0, 9.0, 10.5, 4).as_dict() == {"value": 10.0, "ci": [9.0, 10.5], "ci_half": 0.1,
                                                       "rounds": 4}


def test_p50_interval_pools_the_windows_and_spreads_the_round_medians():
    series = {0: np.array([1.0, 2.0, 3.0]), 1: np.array([4.0, 5.0, 60.0]), 2: np.array([]),
              3: np.array([7.0])}
    assert medians_by_round(series) == {0: 2.0, 1: 5.0, 3: 7.0}
    interval = p50_interval(series)
    assert interval.value == 4.0 and interval.rounds == 3  # the pooled median (mean 11.7); 3 rounds counted
    assert interval == log_interval(4.0, [2.0, 5.0, 7.0], spread=math.sqrt(2))  # where a rerun's would fall
    level = log_interval(4.0, [2.0, 5.0, 7.0])  # the interval of this run's level alone
    assert math.log(interval.high / 4.0) == pytest.approx(math.sqrt(2) * math.log(level.high / 4.0))
    assert p50_interval({}) is None and p50_interval({0: np.array([1.0, 2.0])}) is None


def test_speedup_pairs_the_rounds_both_cells_have():
    baseline = {0: 10.0, 1: 20.0, 2: 12.0, 3: 11.0}
    cell = {0: 5.0, 1: 10.0, 2: 6.0, 4: 1.0}  # drift doubled both in round 1: every paired ratio is 2
    ratio = speedup(baseline, cell)
    assert (ratio.value, ratio.low, ratio.high, ratio.rounds) == (pytest.approx(2.0), pytest.approx(2.0),
                                                                  pytest.approx(2.0), 3)
    uneven = speedup({0: 10.0, 1: 10.0}, {0: 4.0, 1: 5.0})
    assert uneven.value == pytest.approx(math.sqrt(2.5 * 2.0)) and uneven.rounds == 2  # geometric mean
    assert speedup({0: 10.0, 1: 10.0}, {0: 5.0, 2: 5.0}) is None  # one round in common
    assert speedup({0: 10.0, 1: 10.0, 2: 10.0}, {0: 5.0, 1: 0.0, 2: 4.0}).rounds == 2  # a zero time skipped


def test_rate_interval_is_samples_per_second_with_the_spread_of_round_rates():
    interval = rate_interval({0: 90.0, 1: 110.0, 2: 100.0}, samples=3000, seconds=30.0)
    assert interval.value == 100.0 and interval.rounds == 3
    assert interval == log_interval(100.0, [90.0, 110.0, 100.0], spread=math.sqrt(2))  # where a rerun's falls
    assert rate_interval({0: 90.0, 1: 110.0}, samples=3000, seconds=0.0) is None
