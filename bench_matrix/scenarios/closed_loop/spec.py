"""The closed_loop section's types and its fragment of the matrix schema (validated before it is read)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from bench_matrix.matrix.schema import NAME, SELECTION, axis, seconds
from bench_matrix.matrix.spec import Selection
from bench_matrix.workload.driving.circuits import BUILTIN_CIRCUITS
from bench_matrix.workload.driving.margins import Knob
from bench_matrix.workload.driving.perturb import KINDS as PERTURBATIONS
from bench_matrix.workload.driving.points import MAX_COORDINATE
from bench_matrix.workload.driving.simulator import MODES
from bench_matrix.workload.driving.vehicle import SMALL_ROBOT, Response

VEHICLES = {"ideal": Response(), "small_robot": SMALL_ROBOT}  # named responses (docs/closed-loop.md)


@dataclass(frozen=True)
class CircuitSpec:
    """A circuit to drive: a built-in one by name, or a user's closed list of [x, y] points (metres)."""

    name: str
    points: tuple[tuple[float, float], ...] = ()  # empty: the built-in circuit `name`
    lane_width: float = 7.5  # of a user circuit, metres
    time_limit_s: float | None = None  # None: the section's time_limit_s, else the circuit's default


@dataclass(frozen=True)
class MarginSpec:
    """One margin to search: its knob's range on each margin circuit, and for perception what perturbs."""

    kind: str  # latency (ms), speed (factor), perception (strength)
    knob: Knob
    perturbation: str = "mix"
    seed: int = 0


@dataclass(frozen=True)
class MarginsSpec:
    """The `margins` subsection: the margins to search, on which circuits, for which cells."""

    searches: tuple[MarginSpec, ...]
    circuits: tuple[str, ...] = ()  # the section's circuits to search on (every one when empty)
    selection: Selection = Selection()  # of the cells the section drives

    def search_dict(self) -> dict[str, Any]:
        """What a cell's margins depend on (selection aside)."""
        return {"searches": [asdict(m) for m in self.searches], "circuits": list(self.circuits)}


# Each margin's knob as the matrix gives it: (start, default limit, default resolution, unit, limit's maximum)
MARGIN_RANGES = {"latency": (0.0, 500.0, 10.0, "ms", 10_000.0), "speed": (1.0, 2.5, 0.05, "x", 10.0),
                 "perception": (0.0, 1.0, 0.05, "", 2.0)}


@dataclass(frozen=True)
class ClosedLoopSpec:
    """The `closed_loop` section: which cells drive which circuits, in which timing modes, and how."""

    circuits: tuple[CircuitSpec, ...] = (CircuitSpec("simple"),)
    modes: tuple[str, ...] = ("lock_step", "real_time")
    brain_period_ms: float = 50.0
    latency_budget_ms: float = 0.0  # real_time: added to every measured brain time
    time_limit_s: float | None = None  # per circuit, simulated seconds; None: each circuit's default
    off_road_limit_s: float = 2.0
    vehicle: Response = Response()  # how the car answers its commands (the ideal car by default)
    margins: MarginsSpec | None = None  # none searched by default
    selection: Selection = Selection()

    def drive_dict(self) -> dict[str, Any]:
        """How the cells drive (selection and margins aside: a cell's plan adds its margins); the ideal
        vehicle is left out, so results stored before there was a choice keep their fingerprints."""
        left_out = ("selection", "margins") + (("vehicle",) if self.vehicle == Response() else ())
        return {k: v for k, v in asdict(self).items() if k not in left_out}


CIRCUIT = {
    "if": {"type": "string"},
    "then": {"enum": list(BUILTIN_CIRCUITS)},
    "else": {
        "type": "object", "additionalProperties": False, "required": ["name"],
        "properties": {
            "name": NAME,
            "points": {"type": "array", "minItems": 4, "maxItems": 10_000,
                       "description": "a closed circuit's centreline: [x, y] points in metres, in driving "
                                      "order",
                       "items": {"type": "array", "minItems": 2, "maxItems": 2, "items": {
                           "type": "number", "minimum": -MAX_COORDINATE, "maximum": MAX_COORDINATE}}},
            "lane_width": {"type": "number", "minimum": 4, "maximum": 12,
                           "description": "metres (default 7.5)"},
            "time_limit_s": seconds(3_600, exclusive=True),
        },
    },
    "description": "a built-in circuit's name, or {name, points, lane_width} (or {name, time_limit_s})",
}

_MS = {"type": "number", "minimum": 0, "maximum": 2_000}
VEHICLE = {
    "if": {"type": "string"},
    "then": {"enum": list(VEHICLES)},
    "else": {"type": "object", "additionalProperties": False, "minProperties": 1,
             "properties": {"steering_tau_ms": _MS, "speed_tau_ms": _MS, "actuation_delay_ms": _MS,
                            "grip_mps2": {"type": "number", "minimum": 0, "maximum": 100,
                                          "description": "lateral acceleration the tyres hold (0: any)"}}},
    "description": "how the car answers: ideal (default), small_robot, or {steering_tau_ms, ...}",
}


def _search(unit: str, maximum: float, **extra: Any) -> dict[str, Any]:
    """A margin's search: its limit and resolution (in `unit`), and what else it takes."""
    return {"type": "object", "additionalProperties": False, "properties": {
        f"limit{unit}": {"type": "number", "exclusiveMinimum": 0, "maximum": maximum,
                         "description": "the search's end: a cell passing there is reported as passing it"},
        f"resolution{unit}": {"type": "number", "exclusiveMinimum": 0, "maximum": maximum,
                              "description": "the search stops when it has the margin to this"},
        **extra}}


MARGINS = {
    "type": "object", "additionalProperties": False, "minProperties": 1,
    "description": "how far each cell is from failing, searched with lock-step laps (docs/closed-loop.md)",
    "properties": {
        "latency": _search("_ms", 10_000.0),
        "speed": _search("", 10.0),
        "perception": _search("", 2.0, kind={"enum": list(PERTURBATIONS)},
                              seed={"type": "integer", "minimum": 0, "maximum": 2**31 - 1}),
        "circuits": {"type": "array", "minItems": 1, "uniqueItems": True, "items": {"type": "string"},
                     "description": "circuits of the section to search on (default: every one)"},
        **SELECTION,
    },
}

SCHEMA: dict[str, Any] = {
    "type": "object", "additionalProperties": False,
    "description": "drive laps in the built-in simulator with the cells' own artifacts (docs/closed-loop.md)",
    "properties": {
        "circuits": {"type": "array", "minItems": 1, "items": CIRCUIT},
        "modes": axis({"enum": list(MODES)}),
        "brain_period_ms": {"type": "number", "minimum": 1, "maximum": 10_000,
                            "description": "target brain cycle (default 50 ms, the study's)"},
        "latency_budget_ms": {"type": "number", "minimum": 0, "maximum": 10_000,
                              "description": "real_time: added to every measured brain time (a slower "
                                             "target)"},
        "time_limit_s": seconds(3_600, exclusive=True, description="simulated seconds per circuit"),
        "off_road_limit_s": seconds(600, exclusive=True,
                                     description="a lap stops after this long off the road in one go"),
        "vehicle": VEHICLE,
        "margins": MARGINS,
        **SELECTION,
    },
}
