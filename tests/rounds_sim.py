"""A simulated machine for the rounds tests: its own clock, a speed that drifts, seeded noise, and fake
sessions that run on it (nothing reads the real clock)."""

from __future__ import annotations

import random
from collections.abc import Callable

import numpy as np

from bench_matrix.measure.schedule import LATENCY, Rounds, RoundsSettings, SessionLost, Timed, Window

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


def rounds_on(machine: Machine, seed: int = 1, references: dict[str, str] | None = None,
              **settings) -> Rounds:
    return Rounds(RoundsSettings(**settings), rng=random.Random(seed), clock=machine.clock,
                  references=references)


def cells(machine: Machine, names: list[str], processes: int = 1, **session) -> dict[str, list[FakeSession]]:
    """Each name's cell in `processes` fake sessions."""
    return {name: [FakeSession(machine, name, **session) for _ in range(processes)] for name in names}


def round_keys(timed: Timed, kind: str = LATENCY) -> set[int]:
    """The rounds a cell was timed in (any of its processes)."""
    return {r for r, _ in (*timed.kept.get(kind, {}), *timed.dropped.get(kind, {}))}


def one(per_round) -> dict:
    """A single process's values by slot (round, 0)."""
    return {(r, 0): value for r, value in enumerate(per_round)}
