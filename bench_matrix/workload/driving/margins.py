"""How far a driver is from failing: a bisection over one knob (added latency, a factor on the commanded
speed, a camera perturbation's strength), each probe a lap that passes or fails (docs/closed-loop.md)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from .circuit import Track
from .lap import NonFiniteCommand, SimSettings
from .perturb import perturbed
from .simulator import Brain, Simulator

OUTCOMES = ("found", "fails_at_start", "passes_at_limit")
KINDS = ("latency", "speed", "perception")  # the knobs: added ms, factor on speed, perturbation strength


@dataclass(frozen=True)
class Knob:
    """A search's range: `start` (the unchanged lap) to `limit`, on a grid of `resolution`."""

    start: float
    limit: float
    resolution: float

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and self.limit > self.start):
            raise ValueError(f"a search needs limit > start and resolution > 0; got {self}")

    def grid(self, value: float) -> float:
        """The grid point nearest value (start + k × resolution), rounded to hide float noise."""
        return round(self.start + round((value - self.start) / self.resolution) * self.resolution, 9)

    @property
    def top(self) -> float:
        """The limit, raised to the grid."""
        return round(self.start + math.ceil((self.limit - self.start) / self.resolution - 1e-9)
                     * self.resolution, 9)


@dataclass(frozen=True)
class Margin:
    """A search's answer. found: `value` passed and `failed_at` (value + resolution) failed;
    fails_at_start: the unchanged lap failed (no value); passes_at_limit: it never failed up to `value`."""

    outcome: str
    value: float | None
    failed_at: float | None
    resolution: float
    probes: tuple[tuple[float, bool], ...]  # (knob value, passed), in the order driven

    def as_dict(self) -> dict[str, Any]:
        return {"outcome": self.outcome, "value": self.value, "failed_at": self.failed_at,
                "resolution": self.resolution, "probes": [list(probe) for probe in self.probes]}


def search(passes: Callable[[float], bool], knob: Knob) -> Margin:
    """The largest grid value at which `passes` holds, by bisection between the start (which must pass)
    and the limit (which must fail); failure is taken to be monotone in the knob."""
    probes: list[tuple[float, bool]] = []

    def probe(value: float) -> bool:
        probes.append((value, bool(passes(value))))
        return probes[-1][1]

    if not probe(knob.start):
        return Margin("fails_at_start", None, knob.start, knob.resolution, tuple(probes))
    if probe(knob.top):
        return Margin("passes_at_limit", knob.top, None, knob.resolution, tuple(probes))
    good, bad = knob.start, knob.top
    while bad - good > knob.resolution * (1 + 1e-6):
        middle = knob.grid((good + bad) / 2)
        if probe(middle):
            good = middle
        else:
            bad = middle
    return Margin("found", good, bad, knob.resolution, tuple(probes))


def lap_passes(circuit: Track, brain: Brain, settings: SimSettings) -> bool:
    """True when the lap is completed without leaving the road (a NaN or Inf command fails it)."""
    try:
        lap = Simulator(circuit, settings).run(brain)
    except NonFiniteCommand:
        return False
    return lap.stop_reason == "lap_completed" and lap.departures == 0


def lap_probe(kind: str, circuit: Track, brain: Brain, settings: SimSettings, perception: str = "mix",
              seed: int = 0) -> Callable[[float], bool]:
    """Whether a lock-step lap passes with knob `kind` at a value: latency (ms the brain is deemed to take),
    speed (× commanded speeds), perception (`perception` perturbation strength per frame, from `seed`)."""
    lock_step = replace(settings, mode="lock_step", latency_budget_s=0.0)
    if kind == "latency":
        return lambda ms: lap_passes(circuit, brain, replace(lock_step, latency_budget_s=ms / 1e3))
    if kind == "speed":
        return lambda factor: lap_passes(circuit, brain, replace(lock_step, speed_factor=factor))
    if kind == "perception":
        seen = perturbed(brain, perception, seed)
        return lambda strength: lap_passes(circuit, seen(strength), lock_step)
    raise ValueError(f"margin {kind!r}; allowed: {', '.join(KINDS)}")
