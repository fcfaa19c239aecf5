"""How a lap is run (its settings), what it records and how its metrics are computed: checkpoints of the
reference lap, road departures, deviation from the reference line, stop reasons, brain timing
(docs/closed-loop.md defines each)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from .circuit import Pose, Track
from .expert import V_RANGE, W_RANGE
from .vehicle import IDEAL, Response

WINDOW_M = 30.0  # gates further than this ahead of the next one do not count yet (no short cuts)
DEPARTURE_PENALTY = 0.8  # the driving score is multiplied by this for every road departure
# The suddenness normalises commands as the study's labels: v' = (v - 6.5) / 17.5, w' = (w + 7.1) / 14.2
_COMMAND_OFFSET = np.array([V_RANGE[0], W_RANGE[0]])
_COMMAND_SCALE = np.array([V_RANGE[1] - V_RANGE[0], W_RANGE[1] - W_RANGE[0]])


@dataclass(frozen=True)
class SimSettings:
    """How a lap is run (every duration in seconds of simulated time unless said otherwise)."""

    mode: str = "lock_step"  # lock_step: the world waits for the brain; real_time: it does not
    brain_period_s: float = 0.05  # target brain cycle (the study's 50 ms)
    latency_budget_s: float = 0.0  # a slower target: real_time adds it to each measured brain time, lock_step
    # deems every brain step to take exactly this long (0: the world waits)
    physics_step_s: float = 0.01
    time_limit_s: float = 120.0
    off_road_limit_s: float = 2.0  # the run stops once the car has been off the road this long in one go
    stuck_window_s: float = 5.0  # ... or once it moved less than stuck_distance_m in this long
    stuck_distance_m: float = 0.5
    checkpoint_spacing_m: float = 5.0
    trace_spacing_m: float = 1.0  # trajectory points kept at least this far apart
    response: Response = IDEAL  # how the car answers its commands (lags, actuation delay)
    speed_factor: float = 1.0  # every commanded speed is multiplied by this


class NonFiniteCommand(ValueError):
    """The brain answered NaN or Inf: a failure of the run, never a command."""


def gate_crossings(x0: float, y0: float, x1: float, y1: float, centres: np.ndarray, tangents: np.ndarray,
                   reach: float) -> np.ndarray:
    """Which gates the move (x0, y0) -> (x1, y1) crosses forwards: gate i is the segment through centres[i]
    perpendicular to the unit tangents[i], `reach` metres each side."""
    cx, cy, tx, ty = centres[:, 0], centres[:, 1], tangents[:, 0], tangents[:, 1]
    before = (x0 - cx) * tx + (y0 - cy) * ty
    after = (x1 - cx) * tx + (y1 - cy) * ty
    crossed = (before < 0) & (after >= 0)
    fraction = np.where(crossed, before / np.where(crossed, before - after, 1.0), 0.0)
    px, py = x0 + fraction * (x1 - x0), y0 + fraction * (y1 - y0)
    return crossed & (np.abs((py - cy) * tx - (px - cx) * ty) <= reach)


class Checkpoints:
    """`count` gates across the road, evenly along the reference lap's centreline, the last on the start line;
    one counts if crossed forwards within WINDOW_M after the last counted: a skipped one never does."""

    def __init__(self, circuit: Track, spacing: float):
        self.count = max(4, math.ceil(circuit.length / spacing))
        x, y, heading = circuit.pose_at(np.arange(1, self.count + 1) * circuit.length / self.count)
        self.points = np.stack([x, y], 1)
        self.tangents = np.stack([np.cos(heading), np.sin(heading)], 1)
        self.reach = circuit.lane_width / 2
        self.window = max(1, min(math.ceil(WINDOW_M / (circuit.length / self.count)), self.count // 4))
        self.next = 0  # index of the first checkpoint not yet passed
        self.reached = 0

    def update(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        """Count the gates the car crossed moving from (x0, y0) to (x1, y1); True once the last one (the start
        line) is crossed."""
        ahead = slice(self.next, self.next + self.window)
        hits = np.flatnonzero(gate_crossings(x0, y0, x1, y1, self.points[ahead], self.tangents[ahead],
                                             self.reach))
        if len(hits):
            self.reached += len(hits)
            self.next += int(hits[-1]) + 1
        return self.next >= self.count

    @property
    def completed_pct(self) -> float:
        return 100.0 * self.reached / self.count


class LapLog:
    """Everything one lap records, step by step; `summary` turns it into the lap's metrics."""

    def __init__(self, circuit: Track, settings: SimSettings):
        self.settings, self.half_width = settings, circuit.lane_width / 2
        self.stop_reason: str | None = None
        self.time_s = self.distance_m = self.abs_offset_sum = self.max_offset = 0.0
        self.ticks = self.off_road_ticks = self.off_run = self.departures = 0
        self.lap_time_s: float | None = None
        self.completed_pct = 0.0
        self.brain_s: list[float] = []
        self.commands: list[tuple[float, float]] = []
        self.overhead_s: list[float] = []
        self.wall_s = 0.0
        self._recent: deque[tuple[float, float]] = deque(
            maxlen=round(settings.stuck_window_s / settings.physics_step_s) + 1)
        x, y, _ = circuit.pose_at(0.0)
        self.trace: list[tuple[float, float]] = [(float(x), float(y))]

    def brain_step(self, brain_s: float, v: float, w: float) -> None:
        if not (math.isfinite(v) and math.isfinite(w)):
            raise NonFiniteCommand(f"the brain commanded v={v}, w={w} at {self.time_s:.2f} s: not finite")
        self.brain_s.append(brain_s)
        self.commands.append((v, w))

    def overhead(self, seconds: float) -> None:
        self.overhead_s.append(seconds)

    def physics_step(self, time_s: float, pose: Pose, offset: float, driven: float, completed_pct: float,
                     finished: bool) -> None:
        """Record one physics step and decide whether the run stops."""
        self.time_s, self.ticks = time_s, self.ticks + 1
        self.distance_m += driven
        self.abs_offset_sum += abs(offset)
        self.max_offset = max(self.max_offset, abs(offset))
        off = abs(offset) > self.half_width
        self.departures += int(off and self.off_run == 0)
        self.off_run = self.off_run + 1 if off else 0
        self.off_road_ticks += int(off)
        self.completed_pct = completed_pct
        x, y, _ = pose
        self._recent.append((x, y))
        if math.dist(self.trace[-1], (x, y)) >= self.settings.trace_spacing_m:
            self.trace.append((x, y))
        self.stop_reason = self._stop(finished)
        if self.stop_reason is not None and self.trace[-1] != (x, y):
            self.trace.append((x, y))

    def _stop(self, finished: bool) -> str | None:
        s, dt = self.settings, self.settings.physics_step_s
        if finished:
            self.lap_time_s = self.time_s
            return "lap_completed"
        if self.off_run * dt >= s.off_road_limit_s - 1e-9:
            return "off_road"
        if len(self._recent) == self._recent.maxlen and math.dist(self._recent[0], self._recent[-1]) < \
                s.stuck_distance_m:
            return "stuck"
        return "time_limit" if self.time_s >= s.time_limit_s - 1e-9 else None

    def summary(self) -> dict[str, Any]:
        """The lap's metrics (docs/closed-loop.md), JSON-ready; a rate over a zero duration is None."""
        sim = self.time_s
        return {
            "stop_reason": self.stop_reason, "completed_pct": round(self.completed_pct, 3),
            "lap_time_s": self.lap_time_s, "sim_time_s": round(sim, 6), "distance_m": self.distance_m,
            "avg_speed_mps": self.distance_m / sim if sim > 0 else None,
            "deviation_mae_m": self.abs_offset_sum / self.ticks if self.ticks else None,
            "deviation_max_m": self.max_offset,
            "off_road_s": round(self.off_road_ticks * self.settings.physics_step_s, 6),
            "road_departures": self.departures, "brain_steps": len(self.brain_s),
            "brain_hz": len(self.brain_s) / sim if sim > 0 else None,
            "brain_ms": timing_ms(self.brain_s), "sim_overhead_ms": timing_ms(self.overhead_s),
            "wall_s": self.wall_s, "rtf": sim / self.wall_s if self.wall_s > 0 else None,
            "suddenness": suddenness(self.commands),
            "driving_score": driving_score(self.completed_pct, self.departures),
            "trajectory": {"x": [round(x, 2) for x, _ in self.trace],
                           "y": [round(y, 2) for _, y in self.trace]},
        }


def timing_ms(seconds: list[float]) -> dict[str, float] | None:
    """Mean, p50 and p99 (linear interpolation) in milliseconds of every sample; None without samples."""
    if not seconds:
        return None
    ms = np.asarray(seconds) * 1e3
    p50, p99 = np.percentile(ms, [50, 99])
    return {"mean": float(ms.mean()), "p50": float(p50), "p99": float(p99), "n": len(ms)}


def suddenness(commands: list[tuple[float, float]]) -> float | None:
    """Mean L2 distance between consecutive commands, normalised as the study's labels; None below 2."""
    if len(commands) < 2:
        return None
    normalised = (np.asarray(commands) - _COMMAND_OFFSET) / _COMMAND_SCALE
    return float(np.linalg.norm(np.diff(normalised, axis=0), axis=1).mean())


def driving_score(completed_pct: float, departures: int) -> float:
    """Completion (%) times DEPARTURE_PENALTY per road departure."""
    return completed_pct * DEPARTURE_PENALTY ** departures
