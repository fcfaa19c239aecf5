"""The vehicle's response (lags, actuation delay) and the hard built-in circuit, with the geometric expert:
delay degrades a lagged car's driving before it fails; the hairpin circuit needs steering."""

from __future__ import annotations

import numpy as np

from bench_matrix.workload.driving import ExpertController
from bench_matrix.workload.driving.circuits import builtin_circuit, default_time_limit
from bench_matrix.workload.driving.simulator import SimSettings, Simulator
from bench_matrix.workload.driving.vehicle import SMALL_ROBOT


def lap(name: str, brain: object = None, **settings: object) -> dict:
    circuit, expert = builtin_circuit(name), ExpertController()
    drive = brain or (lambda observation: expert.command(circuit, observation.pose))
    simulator = Simulator(circuit, SimSettings(**{"time_limit_s": default_time_limit(circuit), **settings}))
    return simulator.run(drive).summary()


def test_a_delayed_expert_on_a_lagged_car_deviates_more_with_every_delay_before_it_fails() -> None:
    """Lock-step, so each delay is exact: the brain is deemed to take it (the world does not wait)."""
    laps = [lap("oval", response=SMALL_ROBOT, latency_budget_s=ms / 1e3) for ms in (50, 100, 200, 300, 500)]
    *completed, failed = laps
    assert all(one["stop_reason"] == "lap_completed" and one["road_departures"] == 0 for one in completed)
    deviations = [one["deviation_mae_m"] for one in completed]  # 0.019, 0.053, 0.31, 1.0 m
    assert all(later > 1.5 * earlier for earlier, later in zip(deviations, deviations[1:])), deviations
    assert failed["stop_reason"] == "off_road" and failed["completed_pct"] < 100


def test_delay_in_lock_step_lowers_the_brain_rate_exactly() -> None:
    quick, late = (lap("oval", latency_budget_s=ms / 1e3, time_limit_s=5.0) for ms in (0, 150))
    assert quick["brain_steps"] == 100 and late["brain_steps"] == 34  # a step every 150 ms: ceil(5 / 0.15)


def test_the_hairpin_circuit_is_hard_and_needs_steering() -> None:
    circuit = builtin_circuit("hairpin")
    s = np.arange(0.0, circuit.length, 0.5)
    bends = np.abs(circuit.curvature(s))
    assert circuit.road_problem() is None and 15.0 <= 1 / bends.max() < 15.5
    runs = np.split(s[bends < 1e-3], np.flatnonzero(np.diff(s[bends < 1e-3]) > 1) + 1)
    assert max(run[-1] - run[0] for run in runs) > 200  # a straight of more than 200 m
    assert lap("hairpin", brain=lambda _: (10.0, 0.0))["stop_reason"] == "off_road"
