"""A cell's closed-loop laps: the session the offline figures came from drives the built-in simulator on each
circuit in each timing mode; the laps' metrics and decimated trajectories go into the cell's record."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench_matrix.backend import Session
from bench_matrix.data import denormalise
from bench_matrix.phases import phase
from bench_matrix.images import geometric, to_model_input
from bench_matrix.matrix.spec import LabelSpec, Preprocess
from bench_matrix.scenarios.base import Loaded, Outcome
from bench_matrix.scenarios.closed_loop import ClosedLoopPlan
from bench_matrix.scenarios.closed_loop.margins import search_margins
from bench_matrix.scenarios.closed_loop.spec import CircuitSpec, ClosedLoopSpec
from bench_matrix.tensors import SINGLE, TensorSpec, bind
from bench_matrix.workload.driving.circuit import Track
from bench_matrix.workload.driving.circuits import builtin_circuit, default_time_limit, user_circuit
from bench_matrix.workload.driving.lap import NonFiniteCommand, timing_ms
from bench_matrix.workload.driving.simulator import Observation, SimSettings, Simulator

REFERENCE_SPACING_M = 2.0  # the reference line is stored with a point every this many metres


class SessionBrain:
    """The cell's model as a driver: the camera frame through the dataset's preprocessing, one inference at
    batch 1, the outputs de-normalised into raw [v, w]; the time of each inference is kept."""

    def __init__(self, session: Session, preprocess: Preprocess, layout: str, labels: LabelSpec,
                 inputs: tuple[TensorSpec, ...]):
        self.session, self.preprocess, self.layout, self.labels, self.inputs = (
            session, preprocess, layout, labels, inputs)
        self.inference_s: list[float] = []

    def __call__(self, observation: Observation) -> tuple[float, float]:
        image = geometric(observation.frame, self.preprocess)[None]
        inputs = bind({SINGLE: to_model_input(image, self.preprocess, self.layout)}, self.inputs)
        begin = time.perf_counter()
        outputs = self.session.predict(inputs)
        self.inference_s.append(time.perf_counter() - begin)
        v, w = denormalise(np.asarray(outputs[0], np.float64).reshape(-1)[:2], self.labels)
        return float(v), float(w)


def drive_all(loaded: Loaded, plan: ClosedLoopPlan) -> Outcome:
    """Closed-loop record fields: `closed_loop` {circuit: {mode: lap}}, `closed_loop_margins` searched and
    `closed_loop_circuits` {circuit: reference line, size}; or `closed_loop_skipped` (why it cannot drive)."""
    if plan.skip:
        return Outcome({"closed_loop_skipped": plan.skip})
    job = loaded.job
    brain = SessionBrain(loaded.session, job.data.preprocess, job.layout, plan.labels, job.source.inputs)
    laps: dict[str, dict[str, Any]] = {}
    circuits: dict[str, Any] = {}
    searched: dict[str, tuple[Track, SimSettings]] = {}
    for spec in plan.spec.circuits:
        circuit = circuit_of(spec)
        circuits[spec.name] = describe(circuit)
        laps[spec.name] = {}
        for mode in plan.spec.modes:
            phase(f"closed loop · {spec.name} · {mode}")
            laps[spec.name][mode] = drive(circuit, brain, sim_settings(plan.spec, spec, circuit, mode))
        if plan.margins and spec.name in (plan.margins.circuits or (spec.name,)):
            searched[spec.name] = (circuit, sim_settings(plan.spec, spec, circuit, "lock_step"))
    fields = {"closed_loop": laps, "closed_loop_circuits": circuits}
    if plan.margins:
        fields["closed_loop_margins"] = search_margins(brain, plan.margins.searches, searched)
    return Outcome(fields)


def drive(circuit: Track, brain: SessionBrain, settings: SimSettings) -> dict[str, Any]:
    """One lap's metrics, with the settings it ran under; a brain answering NaN or Inf fails the lap."""
    brain.inference_s = []
    try:
        lap = Simulator(circuit, settings).run(brain).summary()
    except NonFiniteCommand as error:
        return {"failed": str(error)}
    return {**lap, "inference_ms": timing_ms(brain.inference_s), "time_limit_s": settings.time_limit_s,
            "brain_period_ms": settings.brain_period_s * 1e3,
            "latency_budget_ms": settings.latency_budget_s * 1e3, "vehicle": settings.response.as_record()}


def circuit_of(spec: CircuitSpec) -> Track:
    """The circuit a matrix names: built-in, or built from the user's points (validated when loaded)."""
    return user_circuit(spec.points, spec.lane_width) if spec.points else builtin_circuit(spec.name)


def sim_settings(section: ClosedLoopSpec, spec: CircuitSpec, circuit: Track, mode: str) -> SimSettings:
    """The simulator's settings for one circuit and mode; the latency budget applies in real time only."""
    limit = spec.time_limit_s or section.time_limit_s or default_time_limit(circuit)
    budget = section.latency_budget_ms / 1e3 if mode == "real_time" else 0.0
    return SimSettings(mode=mode, brain_period_s=section.brain_period_ms / 1e3, latency_budget_s=budget,
                       time_limit_s=float(limit), off_road_limit_s=section.off_road_limit_s,
                       response=section.vehicle)


def describe(circuit: Track) -> dict[str, Any]:
    """What a report needs to draw a circuit: its reference line (decimated), length and road width."""
    x, y, _ = circuit.pose_at(np.arange(0.0, circuit.length, REFERENCE_SPACING_M))
    return {"length_m": round(circuit.length, 3), "lane_width_m": round(circuit.lane_width, 3),
            "reference": {"x": np.round(x, 2).tolist(), "y": np.round(y, 2).tolist()}}
