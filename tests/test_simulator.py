"""The closed-loop simulator without a model: kinematics, geometry against hand-computed cases, checkpoint
gates, stop reasons, the expert on every built-in circuit, determinism and the real-time clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from laps import slowest_rate

from bench_matrix.workload.driving import ExpertController, generate
from bench_matrix.workload.driving.circuits import (
    BUILTIN_CIRCUITS,
    builtin_circuit,
    default_time_limit,
    user_circuit,
)
from bench_matrix.workload.driving.lap import (
    Checkpoints,
    driving_score,
    gate_crossings,
    suddenness,
    timing_ms,
)
from bench_matrix.workload.driving.points import PointCircuit, shape_problem
from bench_matrix.workload.driving.simulator import SimSettings, Simulator
from bench_matrix.workload.driving.vehicle import SMALL_ROBOT, W_GAIN, Car, Response

TIMINGS = ("brain_ms", "sim_overhead_ms", "wall_s", "rtf")  # wall-clock figures, the only ones that vary


def circle(radius: float = 50.0, n: int = 64) -> PointCircuit:
    angle = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return PointCircuit(np.stack([radius * np.cos(angle), radius * np.sin(angle)], 1), lane_width=8.0)


def expert_lap(name: str, **settings: object) -> dict:
    circuit, expert = builtin_circuit(name), ExpertController()
    simulator = Simulator(circuit, SimSettings(**{"time_limit_s": default_time_limit(circuit), **settings}))
    return simulator.run(lambda observation: expert.command(circuit, observation.pose)).summary()


def constant_lap(v: float, w: float, **settings: float) -> dict:
    circuit = builtin_circuit("oval")
    simulator = Simulator(circuit, SimSettings(**{"time_limit_s": 60.0, **settings}))
    return simulator.run(lambda _: (v, w)).summary()


def test_car_drives_exact_arcs() -> None:
    car = Car(0.0, 0.0, 0.0)
    car.command(10.0, 3.5)  # path curvature 3.5 / W_GAIN: a 20 m radius to the left
    radius = W_GAIN / 3.5
    steps = 1000
    driven = sum(car.step(math.pi * radius / 10.0 / steps) for _ in range(steps))  # half a circle
    assert driven == pytest.approx(math.pi * radius)
    assert (car.x, car.y) == pytest.approx((0.0, 2 * radius), abs=1e-9)
    assert car.yaw == pytest.approx(math.pi)
    car.command(-5.0, 99.0)  # the car neither reverses nor turns beyond the label range
    car.step(0.01)
    assert (car.v, car.w) == (0.0, 7.1)


def test_lagged_car_follows_its_command_late_and_first_order() -> None:
    car = Car(0.0, 0.0, 0.0, response=Response(steering_tau_s=0.1, speed_tau_s=0.5, actuation_delay_s=0.02))
    car.command(10.0, 4.0)
    speeds = [(car.step(0.01), car.v, car.w)[1:] for _ in range(12)]
    assert speeds[:2] == [(0.0, 0.0), (0.0, 0.0)]  # 20 ms before the command reaches the actuators
    assert speeds[2] == pytest.approx((10.0 * (1 - math.exp(-0.02)), 4.0 * (1 - math.exp(-0.1))))
    assert speeds[11] == pytest.approx((10.0 * (1 - math.exp(-0.2)), 4.0 * (1 - math.exp(-1.0))))
    fast = Car(0.0, 0.0, 0.0, speed_factor=1.5)
    fast.command(20.0, 0.0)
    fast.step(0.01)
    assert fast.v == 30.0  # the speed factor applies to the clipped command


def test_point_circuit_geometry_matches_a_circle() -> None:
    track = circle()
    assert track.length == pytest.approx(2 * math.pi * 50.0, rel=1e-4)
    assert track.curvature(np.linspace(0, track.length, 50)) == pytest.approx(np.full(50, 1 / 50.0), rel=1e-3)
    for x, y, offset in ((60.0, 0.0, -10.0), (0.0, 47.0, 3.0), (-35.355, -35.355, 0.0)):
        assert track.locate((x, y, 0.0)).offset == pytest.approx(offset, abs=2e-3)
    where = track.locate((0.0, 50.0, math.pi))  # a quarter of the way round, heading along the road
    assert where.s == pytest.approx(track.length / 4, abs=0.01)
    assert where.heading_error == pytest.approx(0, abs=1e-3)


def test_distance_to_the_reference_line_on_the_ovals_straight() -> None:
    oval = builtin_circuit("oval")  # bottom straight along y = -25, driven towards +x (left is +y)
    for x, y, offset in ((0.0, -25.0, 0.0), (5.0, -23.5, 1.5), (-10.0, -29.0, -4.0)):
        assert oval.locate((x, y, 0.0)).offset == pytest.approx(offset, abs=0.02)


def test_gates_count_forward_crossings_within_half_the_road() -> None:
    centres, tangents = np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([[1.0, 0.0], [1.0, 0.0]])
    crossed = gate_crossings(-1.0, 0.5, 1.0, 0.5, centres, tangents, 3.0)
    assert crossed.tolist() == [True, False]
    assert gate_crossings(-1.0, 3.5, 1.0, 3.5, centres, tangents, 3.0).tolist() == [False, False]  # off road
    assert gate_crossings(1.0, 0.0, -1.0, 0.0, centres, tangents, 3.0).tolist() == [False, False]  # backwards
    assert gate_crossings(-1.0, -2.0, 6.0, 2.0, centres, tangents, 3.0).tolist() == [True, True]


def test_checkpoints_in_order_a_skipped_one_never_counts() -> None:
    gates = Checkpoints(circle(), spacing=10.0)  # 32 gates every 9.82 m of a 314 m circle (radius 50)
    assert gates.count == 32 and gates.reach == 4.0
    angle = 2 * math.pi / 32

    def polar(k: float, radius: float = 50.0) -> tuple[float, float]:
        return radius * math.cos(k * angle), radius * math.sin(k * angle)

    assert not gates.update(*polar(0.5), *polar(1.5)) and gates.reached == 1  # gate 1
    gates.update(*polar(1.5, 56.0), *polar(2.5, 56.0))  # gate 2 passed 6 m off the reference line: no count
    gates.update(*polar(2.5), *polar(3.5))  # gate 3 counts; gate 2 never will
    assert (gates.reached, gates.next) == (2, 3)
    gates.update(*polar(2.6), *polar(2.4))  # backwards over gate 3: nothing
    gates.update(*polar(20.5), *polar(21.5))  # beyond the window: nothing
    assert gates.reached == 2 and gates.completed_pct == pytest.approx(100 * 2 / 32)


@pytest.mark.parametrize("response", [Response(), SMALL_ROBOT], ids=["ideal", "small_robot"])
@pytest.mark.parametrize("name", list(BUILTIN_CIRCUITS))
def test_the_expert_completes_every_builtin_circuit(name: str, response: Response) -> None:
    lap = expert_lap(name, response=response)
    assert lap["stop_reason"] == "lap_completed" and lap["completed_pct"] == 100.0
    assert lap["road_departures"] == 0 and lap["off_road_s"] == 0.0
    assert lap["deviation_mae_m"] < 0.2 and lap["deviation_max_m"] < 0.9  # 0.83 m: its 9 m look cuts hairpins
    assert lap["distance_m"] == pytest.approx(builtin_circuit(name).length, rel=0.01)
    assert lap["avg_speed_mps"] == pytest.approx(lap["distance_m"] / lap["sim_time_s"])
    assert lap["brain_hz"] == pytest.approx(20.0, rel=0.01) and lap["driving_score"] == 100.0


def test_lock_step_laps_are_identical() -> None:
    first, second = expert_lap("curvy"), expert_lap("curvy")
    for key in TIMINGS:
        first.pop(key), second.pop(key)
    assert first == second


def test_training_mean_command_leaves_the_road() -> None:
    v, w = generate(200, seed=0, n_circuits=4).labels.mean(axis=0)
    lap = constant_lap(float(v), float(w))
    assert lap["stop_reason"] == "off_road" and lap["completed_pct"] < 50 and lap["road_departures"] == 1


def test_a_car_that_does_not_move_is_stuck() -> None:
    lap = constant_lap(0.0, 0.0)
    assert lap["stop_reason"] == "stuck" and lap["sim_time_s"] == pytest.approx(5.0, abs=0.02)
    assert lap["completed_pct"] == 0 and lap["avg_speed_mps"] == 0


def test_time_limit_stops_a_lap() -> None:
    lap = expert_lap("simple", time_limit_s=3.0)
    assert lap["stop_reason"] == "time_limit" and lap["sim_time_s"] == pytest.approx(3.0)
    assert 0 < lap["completed_pct"] < 20 and lap["lap_time_s"] is None


def test_real_time_latency_lowers_the_brain_rate_and_worsens_the_driving() -> None:
    """Against the same expert in lock-step (the same lap on any machine); the late brain's rate is bounded
    by its measured times, so a busy machine can only make it slower and its driving worse."""
    prompt = expert_lap("twisty", mode="lock_step")
    late = expert_lap("twisty", mode="real_time", latency_budget_s=0.25)
    bound = slowest_rate({**late, "brain_period_ms": 50.0, "latency_budget_ms": 250.0})  # the settings' defaults
    assert prompt["brain_hz"] == pytest.approx(20.0, rel=0.01) and bound <= late["brain_hz"] < 4.1
    assert late["deviation_mae_m"] > 1.3 * prompt["deviation_mae_m"] or late["completed_pct"] < 100


def test_summaries_of_the_lap() -> None:
    assert suddenness([(6.5, -7.1), (24.0, 7.1), (24.0, 7.1)]) == pytest.approx(math.sqrt(2) / 2)
    assert suddenness([(10.0, 0.0)]) is None and timing_ms([]) is None
    assert driving_score(100.0, 0) == 100.0 and driving_score(50.0, 2) == pytest.approx(32.0)
    assert timing_ms([0.001, 0.003]) == {"mean": 2.0, "p50": 2.0, "p99": pytest.approx(2.98), "n": 2}


def test_user_circuits_are_checked() -> None:
    assert "at least 4 points" in shape_problem(np.zeros((3, 2)))
    assert "[x, y] pairs" in shape_problem(np.zeros((5, 3)))
    assert "0.00 m apart" in shape_problem(np.array([[0, 0], [0, 0], [50, 0], [50, 50]], float))
    with pytest.raises(ValueError, match="at least 60 m"):
        user_circuit([[0, 0], [10, 0], [10, 6], [0, 6]], 7.5)
    with pytest.raises(ValueError, match="radius of at least 15 m"):
        user_circuit([[0, 0], [50, 0], [100, 0], [100, 12], [50, 12], [0, 12]], 7.5)  # 6 m hairpins
    assert user_circuit([[0, 0], [100, 0], [100, 60], [0, 60]], 7.0).length > 280
