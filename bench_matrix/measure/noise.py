"""How noisy this machine is for timing (`bench-matrix device check` without a host, docs/devices.md §8): a
few seconds of windows on a tiny model, the spread of their medians, CPU steal, other processes' load, SMT
siblings and the frequency policy; and what that means: the width a cell's p50 reaches per second of
budget."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench_matrix.measure.affinity import SYSFS_CPU, allowed_cpus, cpu_frequency_state
from bench_matrix.measure.interference import Interference, Reading, between, read_counts
from bench_matrix.measure.rounds import t95, window_spread

BUDGETS_S = (3.0, 10.0)  # budgets a cell's width is stated for: the default timing_budget_s, and more
QUIET = {"spread": 0.02, "steal": 0.01, "other": 0.10}  # beyond these the machine is called noisy


@dataclass(frozen=True)
class Rounds:
    """How the rounds spend a cell's budget: each round times each of its `processes` for a latency window of
    `window_s` and a throughput window half as long (the defaults of matrix settings)."""

    window_s: float = 0.1
    processes: int = 2

    def rounds(self, budget_s: float) -> int:
        return max(int(budget_s / (self.processes * self.window_s * 1.5) + 1e-9), 2)

    def width(self, spread: float, budget_s: float) -> float:
        """The half-width of a cell's p50 interval (as the rounds' target counts it) after `budget_s`, its
        windows spreading by `spread`: t95 × the per-round mean's SD ÷ √rounds."""
        n = self.rounds(budget_s)
        return t95(n - 1) * spread / math.sqrt(self.processes) / math.sqrt(n)

    def budget_for(self, spread: float, target: float) -> float:
        """The seconds of budget a cell needs for ±`target` (at most an hour)."""
        budget = self.processes * self.window_s * 1.5 * 2
        while self.width(spread, budget) > target and budget < 3600:
            budget *= 1.1
        return budget


@dataclass(frozen=True)
class Check:
    """What the check saw: each window's median (ms), the interference over it, our CPUs' SMT siblings among
    every CPU, the frequency policy and the load averages."""

    medians_ms: tuple[float, ...]
    interference: Interference
    siblings: Mapping[int, tuple[int, ...]]
    frequency: Mapping[str, object]
    load: tuple[float, ...]
    rounds: Rounds = field(default_factory=Rounds)

    @property
    def spread(self) -> float:
        """The windows' spread over the whole check, a robust relative SD (the log medians' MAD × 1.4826)."""
        logs = np.log(np.asarray(self.medians_ms))
        return 1.4826 * float(np.median(np.abs(logs - np.median(logs))))

    @property
    def step(self) -> float:
        """How far one window is from the next (drift cancels): the rounds' window_spread."""
        return window_spread({(r, 0): math.log(m) for r, m in enumerate(self.medians_ms)}) or 0.0

    @property
    def drift(self) -> float:
        """The last third's median over the first third's, less 1."""
        third = max(len(self.medians_ms) // 3, 1)
        return float(np.median(self.medians_ms[-third:]) / np.median(self.medians_ms[:third]) - 1)

    def shared(self) -> list[int]:
        """Our CPUs whose SMT siblings may run other work (another CPU on the same core)."""
        return [cpu for cpu, found in sorted(self.siblings.items()) if len(found) > 1]

    def verdict(self) -> str:
        """'quiet', or 'noisy: ' and why."""
        why = [text for value, limit, text in (
            (self.spread, QUIET["spread"], f"windows spread {self.spread:.1%}"),
            (self.interference.steal_share, QUIET["steal"], f"CPU steal {self.interference.steal_share:.1%}"),
            (self.interference.machine_share, QUIET["other"],
             f"other processes took {self.interference.machine_share:.0%} of the machine"))
               if value > limit]
        return "noisy: " + "; ".join(why) if why else "quiet"

    def rows(self) -> list[tuple[str, str]]:
        """(field, value) rows, in the order shown."""
        windows = f"{len(self.medians_ms)} of {self.rounds.window_s:g} s on a tiny ONNX model, 1 thread"
        widths = ", ".join(f"±{self.rounds.width(self.spread, b):.1%} in {b:g} s" for b in BUDGETS_S)
        return [("windows", windows), ("median", f"{np.median(self.medians_ms):.4g} ms a call"),
                ("spread", f"{self.spread:.2%} over the check, {self.step:.2%} window to window, drift "
                           f"{self.drift:+.1%} (last third vs first)"),
                ("CPU steal", f"{self.interference.steal_share:.1%}"),
                ("other processes", f"{self.interference.machine_share:.0%} of the machine's CPU time; load "
                                    + " ".join(f"{v:g}" for v in self.load)),
                ("SMT siblings", _siblings(self.siblings, self.shared())),
                ("frequency", _frequency(self.frequency)),
                ("a cell's p50", f"{widths} of budget (timing_budget_s, {self.rounds.processes} processes), "
                                 f"±2 % in {self.rounds.budget_for(self.spread, 0.02):.0f} s: the rounds' "
                                 "part of its width; how its processes differ comes on top"),
                ("verdict", self.verdict())]

    def to_json(self) -> dict[str, object]:
        return {"windows": len(self.medians_ms), "window_s": self.rounds.window_s,
                "median_ms": float(np.median(self.medians_ms)), "spread": round(self.spread, 6),
                "window_spread": round(self.step, 6), "drift": round(self.drift, 6),
                "interference": self.interference.as_dict(), "smt_shared": self.shared(),
                "siblings": {str(c): list(s) for c, s in self.siblings.items()},
                "frequency": dict(self.frequency), "load": list(self.load),
                "width": {f"{b:g}": round(self.rounds.width(self.spread, b), 6) for b in BUDGETS_S},
                "budget_for_2pct_s": round(self.rounds.budget_for(self.spread, 0.02), 1),
                "verdict": self.verdict()}


def check(window: Callable[[float], float], seconds: float, rounds: Rounds = Rounds(),
          clock: Callable[[], float] | None = None, read: Callable[[], Reading] = read_counts,
          sysfs: Path = SYSFS_CPU, loadavg: Path = Path("/proc/loadavg"), cpus: tuple[int, ...] | None = None
          ) -> Check:
    """Time `window(window_s)` (a window's median, ms) for `seconds` (≥ 3 windows), then read machine facts
    (`cpus`: whose SMT siblings; default: all this process may use); clock, readings, files injectable."""
    import time

    clock = clock or time.perf_counter
    begin, start, medians = read(), clock(), []
    while len(medians) < 3 or clock() - start < seconds:
        medians.append(window(rounds.window_s))
    found = between(begin, read())
    return Check(tuple(medians), found, siblings(cpus or allowed_cpus(), sysfs), cpu_frequency_state(sysfs),
                 _load(loadavg), rounds)


def siblings(cpus: tuple[int, ...], sysfs: Path = SYSFS_CPU) -> dict[int, tuple[int, ...]]:
    """Each of `cpus` with the CPUs sharing its core (thread_siblings_list; itself alone where not
    exposed)."""
    return {cpu: _cpu_list(sysfs / f"cpu{cpu}" / "topology" / "thread_siblings_list") or (cpu,)
            for cpu in cpus}


def _cpu_list(path: Path) -> tuple[int, ...]:
    """'0-1,4' as (0, 1, 4); () where unreadable."""
    try:
        text = path.read_text().strip()
    except OSError:
        return ()
    found: list[int] = []
    for part in filter(None, text.split(",")):
        low, _, high = part.partition("-")
        found += range(int(low), int(high or low) + 1)
    return tuple(found)


def _load(path: Path) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in path.read_text().split()[:3])
    except (OSError, ValueError):
        return ()


def _siblings(found: Mapping[int, tuple[int, ...]], shared: list[int]) -> str:
    if not shared:
        cpus = ", ".join(map(str, found))
        return f"none: each of CPU {cpus} has its core to itself (as far as sysfs shows)"
    return "; ".join(f"CPU {cpu} shares its core with CPU {', '.join(str(c) for c in found[cpu] if c != cpu)}"
                     for cpu in shared) + ": work there slows the timed one (up to 40 %)"


def _frequency(state: Mapping[str, object]) -> str:
    governor = state.get("scaling_governor")
    governors = sorted(set(governor.values())) if isinstance(governor, dict) else [str(governor)]
    return (f"governor {'/'.join(governors)}, boost {state.get('boost')}, intel no_turbo "
            f"{state.get('intel_no_turbo')}")
