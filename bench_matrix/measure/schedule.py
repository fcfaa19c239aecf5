"""The rounds scheduler (docs/metrics.md §5): the harness owns the clock. A model's loaded sessions (each cell
in one or more processes) are timed in short windows, round by round, each round visiting every process of
every cell once (the baseline's more often) in a fresh random order; a cell leaves once its p50 and speed-up
intervals are narrow enough and its answer is settled (the budget goes to the answers still open), until
none is left or the time budget is spent; as many cells are alive at once as fit the memory budget, the
baseline in every group."""

from __future__ import annotations

import math
import random
import time
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import numpy as np

from bench_matrix.measure.rounds import (Interval, Level, Slot, Spread, level_width, log_levels, p50_interval,
                                         pooled, process_spread, speedup, steady, window_level)

LATENCY = "latency"  # the kind of window whose intervals decide when the rounds stop


@dataclass(frozen=True)
class Window:
    """One cell's timed window of one kind: each call's (or batch's) duration in ms, the samples each call
    carries, and why other work disturbed it (None: it did not)."""

    kind: str
    durations_ms: np.ndarray
    samples: int = 1
    disturbed: str | None = None
    interference: dict[str, object] = field(default_factory=dict)

    @cached_property
    def level(self) -> Level:
        """Its median and that median's own error, computed once (the rounds ask every round)."""
        return window_level(self.durations_ms)


class SessionLost(Exception):
    """A session's process crashed, hung or failed: its cell fails with this reason, the others go on."""


class Session(Protocol):
    """A loaded cell, kept alive between windows (its own process)."""

    kinds: tuple[str, ...]  # the kinds of window it times, each round in this order
    rss_mb: float  # its resident memory once loaded and warmed up

    def window(self, kind: str) -> Window:
        """Time one window of `kind` now (a short warm-up first); SessionLost when the session is gone."""


LOOSE = 0.05  # the precision a cell whose answer is settled leaves at, unless the user asks for another


@dataclass(frozen=True)
class RoundsSettings:
    """When rounds stop: all intervals within ±`target` after `min_rounds` (`asked`: the user's, binding every
    cell), or `budget_s`/`max_rounds` spent; a cell disturbed over `disturbed_share` is marked; `window_s`."""

    min_rounds: int = 5
    max_rounds: int = 200
    budget_s: float = 60.0
    target: float = LOOSE
    disturbed_share: float = 0.25
    window_s: float = 0.2
    asked: bool = False


Cell = Sequence[Session]  # a cell's session processes, each timed once per round


@dataclass
class Timed:
    """What the rounds gave one cell: its windows by kind and slot (round, process), clean ones kept,
    disturbed ones apart; why it failed, and how its rounds ended."""

    kept: dict[str, dict[Slot, Window]] = field(default_factory=dict)
    dropped: dict[str, dict[Slot, Window]] = field(default_factory=dict)
    failed: str | None = None
    stop: str = ""  # "width": every interval narrow enough; "budget": time ran out; "rounds": max_rounds
    open: str | None = None  # why its answer was still open when it last was in the rounds (None: settled)
    counts: Counter[tuple[str, bool]] = field(default_factory=Counter)  # windows by (kind, disturbed)

    def add(self, slot: Slot, window: Window) -> None:
        """Keep `window` (or drop it, disturbed) at `slot`; a second visit of the slot joins its calls."""
        windows = (self.kept if window.disturbed is None else self.dropped).setdefault(window.kind, {})
        windows[slot] = _joined(windows[slot], window) if slot in windows else window
        self.counts[window.kind, window.disturbed is not None] += 1

    def count(self, kind: str) -> tuple[int, int]:
        """The windows of `kind` timed, and how many of them were disturbed."""
        return self.counts[kind, False] + self.counts[kind, True], self.counts[kind, True]

    def visits(self, kind: str = LATENCY) -> float:
        """The windows of `kind` timed per slot, on average (above 1: the baseline's repeat visits)."""
        slots = {*self.kept.get(kind, {}), *self.dropped.get(kind, {})}
        return self.count(kind)[0] / len(slots) if slots else 0.0

    def windows(self, kind: str, clean: bool = False, every: bool = False) -> dict[Slot, Window]:
        """The windows a figure is computed from, by slot: the clean ones, or (unless `clean`) every one when
        fewer than 2 rounds were clean, or when `every`."""
        kept = self.kept.get(kind, {})
        enough = len({r for r, _ in kept}) >= 2
        chosen = kept if clean or (enough and not every) else {**self.dropped.get(kind, {}), **kept}
        return dict(sorted(chosen.items()))

    def series(self, kind: str, clean: bool = False, every: bool = False) -> dict[Slot, np.ndarray]:
        """Those windows' durations in ms, by slot."""
        return {slot: w.durations_ms for slot, w in self.windows(kind, clean, every).items()}

    def levels(self, kind: str, clean: bool = False, every: bool = False) -> dict[Slot, Level]:
        """Those windows' `Level`s (median, its own error), by slot."""
        return {slot: w.level for slot, w in self.windows(kind, clean, every).items() if len(w.durations_ms)}

    def medians(self, kind: str, clean: bool = False, every: bool = False) -> dict[Slot, float]:
        """Those windows' medians, by slot."""
        return {slot: level.median for slot, level in self.levels(kind, clean, every).items()}

    def rounds(self, kind: str = LATENCY) -> int:
        """The rounds whose windows its figures of `kind` pool."""
        return len({r for r, _ in self.windows(kind)})


def _joined(first: Window, second: Window) -> Window:
    """Two windows of one slot as one: their calls together (the first's reason, if disturbed)."""
    return Window(first.kind, np.concatenate([first.durations_ms, second.durations_ms]), first.samples,
                  first.disturbed, first.interference)


def spread(cells: Iterable[Timed], kind: str = LATENCY, rate: bool = False) -> Spread | None:
    """How the session processes of a model's cells differ in `kind`'s windows (their medians, or their
    `rate`s), pooled over the cells (from their clean windows)."""
    def levels(timed: Timed) -> dict[Slot, float]:
        return rates(timed.windows(kind, clean=True)) if rate else timed.medians(kind, clean=True)

    return pooled(process_spread(steady(log_levels(levels(t)), rate)) for t in cells)


def rates(windows: Mapping[Slot, Window]) -> dict[Slot, float]:
    """Samples per second of each window (a throughput window's batches)."""
    return {slot: w.samples * len(w.durations_ms) / (float(w.durations_ms.sum()) / 1e3)
            for slot, w in windows.items() if float(w.durations_ms.sum()) > 0}


def paired(baseline: Timed | None, timed: Timed, model: Spread | None = None,
           clean: bool = False) -> Interval | None:
    """The cell's speed-up against the baseline, paired by round: over the rounds both had clean, or (unless
    `clean`) every round both had when fewer than 2 were clean: what disturbs a round disturbs both."""
    if baseline is None:
        return None
    found = speedup(*(t.medians(LATENCY, clean=True) for t in (baseline, timed)), model)
    if found is not None or clean:
        return found
    return speedup(*(t.medians(LATENCY, every=True) for t in (baseline, timed)), model)


def narrow(timed: Timed, baseline: Timed | None, settings: RoundsSettings,
           model: Spread | None = None) -> bool:
    """Whether the cell's p50 interval (and speed-up interval, beside a baseline) is within the target after
    the minimum number of clean rounds (`model`: the model's pooled process spread)."""
    p50 = p50_interval(timed.series(LATENCY, clean=True), model, timed.levels(LATENCY, clean=True))
    if p50 is None or p50.rounds < settings.min_rounds or level_width(p50) > settings.target:
        return False
    if baseline is None or baseline is timed:
        return True
    ratio = paired(baseline, timed, model, clean=True)
    return ratio is not None and ratio.rounds >= settings.min_rounds and ratio.half_width <= settings.target


class Answers(Protocol):
    """What the rounds are for: which cells' answers (a verdict, the recommendation) are still open."""

    def open(self, timed: Mapping[str, Timed], live: Collection[str]) -> dict[str, str]:
        """The cells of `live` whose answer their figures so far leave open, each with why."""


class Rounds:
    """Runs the rounds of a model's cells: `rng` orders each, `clock` (s) times the budget, `hold` (the timing
    lock) wraps each group's, `on_round` hears each begin; `references`: pairings other than the baseline."""

    def __init__(self, settings: RoundsSettings, rng: random.Random | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 hold: Callable[[], AbstractContextManager] = nullcontext,
                 on_round: Callable[[int], None] = lambda number: None,
                 references: Mapping[str, str] | None = None, answers: Answers | None = None):
        self.settings, self.rng, self.clock = settings, rng or random.Random(), clock
        self.hold, self.on_round, self.references = hold, on_round, dict(references or {})
        self.answers = answers  # keeps cells with an open answer in the rounds (None: all leave once narrow)
        self.number = 0  # rounds run so far, over every group (the baseline's rounds are numbered so)
        self.orders: list[tuple[str, ...]] = []  # each round's cells in the order timed (one per visit)

    def run(self, sessions: Mapping[str, Cell], timed: dict[str, Timed], baseline: str | None,
            budget_s: float) -> str:
        """Rounds over `sessions` (each cell's processes) until every cell has left them narrow enough, or
        `budget_s` is spent; why they stopped. A lost session fails its cell, which leaves the rounds."""
        with self.hold():
            live = dict(sessions)
            start, count, settled = self.clock(), 0, False
            while live:
                self._round(live, timed, baseline)
                count += 1
                settled = self._settle(live, timed, baseline) or settled
                if not live:
                    break
                if count >= self.settings.max_rounds:
                    return "rounds"
                if self.clock() - start >= budget_s and count >= 2:
                    return "budget"
            return "width" if settled else "failed"

    def _settle(self, live: dict[str, Cell], timed: dict[str, Timed], baseline: str | None) -> bool:
        """Cells narrow enough whose answer is settled leave the rounds (their stop: width), the budget going
        to the others; a cell stays while another still in them is paired against it. Whether any left."""
        def reference(key: str) -> str | None:
            return self.references.get(key, baseline)

        def against(key: str) -> Timed | None:
            return timed[reference(key)] if reference(key) in live else None

        model = spread(timed.values())
        still = self._open(live, timed)
        leaving = {key for key in live
                   if key not in still and narrow(timed[key], against(key), self.settings, model)}
        while needed := leaving & {reference(key) for key in live if key not in leaving}:
            leaving -= needed
        for key in leaving:
            timed[key].stop = "width"
            del live[key]
        return bool(leaving)

    def _open(self, live: Mapping[str, Cell], timed: dict[str, Timed]) -> dict[str, str]:
        """The live cells whose answer is open (kept on each cell's Timed too); none before `min_rounds`."""
        ready = min((timed[key].rounds() for key in live), default=0) >= self.settings.min_rounds
        if self.answers is None or not ready:
            return {}
        still = self.answers.open(timed, live)
        for key in live:
            timed[key].open = still.get(key)
        return still

    def visits(self, live: Mapping[str, Cell], baseline: str | None) -> dict[str, int]:
        """Per-round visits to each process of a cell: 1, or round(√n) if n others pair against it, as all
        share its level (Dunnett: n comparisons with one control vary least at √n× its samples)."""
        against = Counter(reference for key in live
                          if (reference := self.references.get(key, baseline)) in live and reference != key)
        return {key: max(1, round(math.sqrt(against[key]))) for key in live}

    def _round(self, live: dict[str, Cell], timed: dict[str, Timed], baseline: str | None) -> None:
        """One round: every visit in a fresh random order; a process's first visit times each of its kinds,
        a repeat its latency only (what the speed-ups pair)."""
        visits = self.visits(live, baseline)
        units = [(key, process) for key in sorted(live) for process in range(len(live[key]))
                 for _ in range(visits[key])]
        order = self.rng.sample(units, len(units))
        self.orders.append(tuple(key for key, _ in order))
        self.on_round(self.number)
        visited: set[tuple[str, int]] = set()
        for key, process in order:
            if key not in live:  # another of its processes was lost this round
                continue
            try:
                session = live[key][process]
                repeat = (key, process) in visited
                visited.add((key, process))
                for kind in (kind for kind in session.kinds if not repeat or kind == LATENCY):
                    timed[key].add((self.number, process), session.window(kind))
            except SessionLost as lost:
                timed[key].failed = str(lost)
                del live[key]
        self.number += 1


def measure_groups(keys: list[str], baseline: str | None, open_session: Callable[[str], Cell],
                   close: Callable[[str, Cell], None], memory_mb: float,
                   rounds: Rounds) -> dict[str, Timed]:
    """Time `keys` in groups within `memory_mb` resident, the baseline (opened first) in each, budget split by
    cells; `open_session` loads a cell's processes, `close` ends them after its rounds (baseline's last)."""
    timed = {key: Timed() for key in keys}
    base = _opened(baseline, open_session, timed) if baseline in timed else None
    waiting = [key for key in keys if key != baseline]
    share = rounds.settings.budget_s / max(len(waiting), 1)
    stop, largest = "failed", 0.0
    while True:
        group = {baseline: base} if base is not None else {}
        while waiting and (len(group) < 1 + (base is not None) or _rss(group) + largest <= memory_mb):
            key = waiting.pop(0)
            if session := _opened(key, open_session, timed):
                group[key], largest = session, max(largest, _rss({key: session}))
        members = [key for key in group if key != baseline]
        if members or (base is not None and not waiting and not _timed(timed[baseline])):
            stop = rounds.run(group, timed, baseline if base is not None else None,
                              share * max(len(members), 1))
        for key in members:
            _end(key, group[key], timed, stop, close)
        if base is not None and timed[baseline].failed:
            _end(baseline, base, timed, stop, close)
            base = None
        if not waiting:
            break
    if base is not None:
        _end(baseline, base, timed, stop, close)
    return timed


def _timed(cell: Timed) -> bool:
    return bool(cell.kept or cell.dropped)


def _rss(group: Mapping[str, Cell]) -> float:
    return sum(session.rss_mb for cell in group.values() for session in cell)


def _opened(key: str, open_session: Callable[[str], Cell], timed: dict[str, Timed]) -> Cell | None:
    try:
        return open_session(key)
    except SessionLost as lost:
        timed[key].failed = str(lost)
        return None


def _end(key: str, session: Cell, timed: dict[str, Timed], stop: str, close: Callable[[str, Cell], None]
         ) -> None:
    if not timed[key].stop:
        timed[key].stop = stop
    close(key, session)
