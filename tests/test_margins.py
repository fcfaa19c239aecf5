"""The margin search (bisection over a knob, each probe a lap) on stub drivers with known failure points,
its explicit outcomes when nothing or everything passes, and the camera perturbations (deterministic)."""

from __future__ import annotations

import numpy as np
import pytest

from bench_matrix.workload.driving import ExpertController, render
from bench_matrix.workload.driving.circuits import builtin_circuit, default_time_limit
from bench_matrix.workload.driving.lap import SimSettings
from bench_matrix.workload.driving.margins import Knob, lap_probe, search
from bench_matrix.workload.driving.perturb import KINDS, PerturbedCamera, perturb
from bench_matrix.workload.driving.render import Lighting
from bench_matrix.workload.driving.simulator import Observation
from bench_matrix.workload.driving.vehicle import SMALL_ROBOT


def frame() -> np.ndarray:
    circuit = builtin_circuit("oval")
    return render(circuit, tuple(float(v) for v in circuit.pose_at(0.0)), Lighting())


def test_bisection_finds_a_known_failure_point_to_its_resolution() -> None:
    margin = search(lambda ms: ms <= 137, Knob(0.0, 500.0, 10.0))
    assert (margin.outcome, margin.value, margin.failed_at) == ("found", 130.0, 140.0)
    assert margin.resolution == 10.0
    assert margin.probes[:2] == ((0.0, True), (500.0, False)) and len(margin.probes) == 2 + 6  # log2(50)
    assert all(round(value / 10) * 10 == value for value, _ in margin.probes)  # on the grid


def test_a_driver_failing_everywhere_or_nowhere_is_reported_as_such() -> None:
    never = search(lambda _: False, Knob(1.0, 2.0, 0.05))
    assert (never.outcome, never.value, never.failed_at, never.probes) == ("fails_at_start", None, 1.0,
                                                                           ((1.0, False),))
    always = search(lambda _: True, Knob(0.0, 0.98, 0.05))  # the limit is raised to the grid: 1.0
    assert (always.outcome, always.value, always.failed_at) == ("passes_at_limit", 1.0, None)
    assert always.as_dict()["probes"] == [[0.0, True], [1.0, True]]
    with pytest.raises(ValueError, match="resolution > 0"):
        Knob(0.0, 1.0, 0.0)


def test_latency_and_speed_margins_of_the_expert_on_a_lagged_car() -> None:
    """Every probe a lock-step lap (the settings' real time is overridden): 200 ms late it completes the oval,
    400 ms late it leaves the road; 1.5 times as fast it completes, twice as fast its tyres let go."""
    circuit, expert = builtin_circuit("oval"), ExpertController()
    settings = SimSettings(time_limit_s=default_time_limit(circuit), response=SMALL_ROBOT, mode="real_time")
    brain = lambda seen: expert.command(circuit, seen.pose)  # noqa: E731
    margin = search(lap_probe("latency", circuit, brain, settings), Knob(200.0, 400.0, 100.0))
    assert (margin.outcome, margin.value, margin.failed_at) == ("found", 300.0, 400.0), margin
    faster = lap_probe("speed", circuit, brain, settings)
    assert faster(1.5) and not faster(2.0)


def test_a_driver_blinded_by_dusk_has_a_perception_margin_where_it_goes_blind() -> None:
    """It steers as the expert while the frame keeps half its mean brightness, else drives straight: light
    keeps 1 - 0.75 × strength of it, so it fails above strength 2/3."""
    circuit, expert = builtin_circuit("oval"), ExpertController()
    daylight = frame().mean()

    def driver(seen: Observation) -> tuple[float, float]:
        return expert.command(circuit, seen.pose) if seen.frame.mean() >= daylight / 2 else (10.0, 0.0)

    probe = lap_probe("perception", circuit, driver, SimSettings(time_limit_s=70.0), perception="light")
    margin = search(probe, Knob(0.0, 1.0, 0.25))
    assert (margin.outcome, margin.value, margin.failed_at) == ("found", 0.5, 0.75), margin


@pytest.mark.parametrize("kind", KINDS)
def test_perturbations_are_deterministic_from_seed_and_step(kind: str) -> None:
    image = frame()
    first, again = perturb(image, kind, 0.5, 7, 3), perturb(image, kind, 0.5, 7, 3)
    assert first.dtype == np.uint8 and np.array_equal(first, again) and not np.array_equal(first, image)
    assert np.array_equal(perturb(image, kind, 0.0, 7, 3), image)
    stronger = np.abs(perturb(image, kind, 1.0, 7, 3).astype(int) - image).mean()
    assert stronger > np.abs(first.astype(int) - image).mean()
    if kind in ("noise", "mix"):
        assert not np.array_equal(perturb(image, kind, 0.5, 7, 4), first)  # another step, other noise
        assert not np.array_equal(perturb(image, kind, 0.5, 8, 3), first)


def test_every_cell_sees_the_same_perturbation_at_the_same_step() -> None:
    """Two cells' brains (whatever they answer) are handed identical frames, step by step."""
    seen: dict[str, list[np.ndarray]] = {"a": [], "b": []}
    def brain(cell: str) -> object:
        return lambda o: (seen[cell].append(o.frame), (1.0, 0.0))[1]

    cameras = {cell: PerturbedCamera(brain(cell), "mix", 0.4, 0) for cell in seen}
    image = frame()
    for _ in range(3):
        for camera in cameras.values():
            camera(Observation(image, (0.0, 0.0, 0.0)))
    assert all(np.array_equal(a, b) for a, b in zip(seen["a"], seen["b"]))
    assert not np.array_equal(seen["a"][0], seen["a"][1])
