"""The named built-in circuits of the closed-loop evaluation, and user circuits given as points."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .circuit import Circuit, Track
from .layouts import Segment, closed_layout
from .points import PointCircuit

MIN_AVERAGE_SPEED = 4.0  # m/s: the default time limit of a circuit is its length at this speed


@dataclass(frozen=True)
class BuiltinCircuit:
    """A named circuit: a procedural seed (none of the training data's circuits), a layout or a small oval."""

    description: str
    seed: int | None = None  # procedural Circuit.from_seed(seed); None: the layout, else the oval
    layout: tuple[Segment, ...] = ()  # straights and arcs (layouts.py), its two longest straights closing it


# The study's Montreal in spirit: a 245 m straight (after an S-bend) into a hairpin, two chicanes, a sweeping
# return; arcs drawn 15 % wider than the 15 m the spline's curvature overshoots to at their ends (15.1 m)
HAIRPIN_LAYOUT = ((0.0, 20.0), (20.0, 45.0), (20.0, -45.0), (0.0, 220.0), (17.3, 180.0), (0.0, 50.0),
                  (19.0, -60.0), (19.0, 60.0), (0.0, 30.0), (19.0, -60.0), (19.0, 60.0), (0.0, 0.0),
                  (25.0, 90.0), (0.0, 0.0), (25.0, 90.0))


# Seeds chosen for their bends (max |curvature| 1/m, mean |curvature|): simple 0.032 / 0.0150, curvy 0.043 /
# 0.0202, twisty 0.052 / 0.0233; the training circuits are drawn from 31-bit seeds, never these.
BUILTIN_CIRCUITS = {
    "oval": BuiltinCircuit("277 m stadium: two 60 m straights, two bends of 25 m radius (quick tests)"),
    "simple": BuiltinCircuit("488 m, gentle bends (tightest radius 31 m)", seed=4),
    "curvy": BuiltinCircuit("387 m, medium bends (tightest radius 23 m)", seed=1),
    "twisty": BuiltinCircuit("372 m, the tightest bends (radius 19 m) and the most turning", seed=0),
    "hairpin": BuiltinCircuit("721 m, a long straight into a 15 m hairpin, S-bends and chicanes at 15-16 m "
                              "radius (the study's Montreal in spirit)", layout=HAIRPIN_LAYOUT),
}


def oval_points(straight: float = 60.0, radius: float = 25.0, spacing: float = 5.0) -> np.ndarray:
    """Points every `spacing` metres around a stadium: straights along x, semicircular ends, anticlockwise."""
    half = straight / 2
    line = np.arange(-half, half, spacing)
    bend = np.linspace(-np.pi / 2, np.pi / 2, int(np.ceil(np.pi * radius / spacing)), endpoint=False)
    right = np.stack([half + radius * np.cos(bend), radius * np.sin(bend)], 1)
    return np.vstack([np.stack([line, np.full_like(line, -radius)], 1), right,
                      np.stack([-line, np.full_like(line, radius)], 1), -right])


@lru_cache(maxsize=16)
def builtin_circuit(name: str) -> Track:
    """The built-in circuit `name` (KeyError when there is none), built once per process."""
    spec = BUILTIN_CIRCUITS[name]
    if spec.seed is not None:
        return Circuit.from_seed(spec.seed)
    if spec.layout:
        return PointCircuit(closed_layout(list(spec.layout), (11, 13)), lane_width=7.5)
    return PointCircuit(oval_points(), lane_width=7.5)


def user_circuit(points: Sequence[Sequence[float]], lane_width: float) -> PointCircuit:
    """A circuit through a user's points (ValueError saying why it cannot be one)."""
    circuit = PointCircuit(points, lane_width=lane_width)
    if problem := circuit.road_problem():
        raise ValueError(problem)
    return circuit


def default_time_limit(circuit: Track) -> float:
    """Seconds of simulated time a lap may take by default: the length at MIN_AVERAGE_SPEED, rounded up."""
    return float(np.ceil(circuit.length / MIN_AVERAGE_SPEED))
