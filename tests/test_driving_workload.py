"""Behaviour of the synthetic driving workload: circuits, renderer, expert labels and data set."""

from __future__ import annotations

import numpy as np
import pytest

from bench_matrix.workload.driving import (
    BEND_CLASSES,
    Camera,
    Circuit,
    DrivingData,
    ExpertController,
    Lighting,
    bend_classes,
    generate,
    render,
)

N_CIRCUITS = 8


@pytest.fixture(scope="module")
def data() -> DrivingData:
    return generate(800, seed=0, n_circuits=N_CIRCUITS)


@pytest.fixture(scope="module")
def circuit() -> Circuit:
    return Circuit.from_seed(11)


def _pose(circuit: Circuit, s: float, offset: float = 0.0,
          yaw_error: float = 0.0) -> tuple[float, float, float]:
    x, y, heading = circuit.pose_at(s, offset)
    return float(x), float(y), float(heading) + yaw_error


def _straightest(circuit: Circuit, window: float = 40.0) -> float:
    """Arc length whose next `window` metres have the smallest peak |curvature|."""
    s = np.arange(0.0, circuit.length, 1.0)
    peak = np.abs(circuit.curvature(s[:, None] + np.linspace(-10.0, window, 50))).max(axis=1)
    return float(s[np.argmin(peak)])


def test_generate_is_deterministic_per_seed() -> None:
    a, b = generate(24, seed=3, n_circuits=2), generate(24, seed=3, n_circuits=2)
    c = generate(24, seed=4, n_circuits=2)
    for field in ("images", "labels", "groups"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.images, c.images)
    assert not np.array_equal(a.labels, c.labels)


def test_shapes_dtypes_and_label_ranges(data: DrivingData) -> None:
    assert len(data) == 800
    assert data.images.shape == (800, 66, 200, 3) and data.images.dtype == np.uint8
    assert data.labels.shape == (800, 2) and data.labels.dtype == np.float32
    assert data.groups.shape == (800,) and data.groups.dtype == np.int32
    v, w = data.labels.T
    assert v.min() >= 6.5 and v.max() <= 24.0
    assert w.min() >= -7.1 and w.max() <= 7.1


def test_labels_are_spread_out(data: DrivingData) -> None:
    v, w = data.labels.T
    assert w.std() > 2.0
    assert (w < -1.0).mean() > 0.2 and (w > 1.0).mean() > 0.2
    assert v.std() > 2.0 and v.max() - v.min() > 12.0
    clipped = (np.abs(w) > 7.09).mean()
    assert clipped < 0.1


def test_bend_classes_are_five_reasonably_balanced(data: DrivingData) -> None:
    shares = np.bincount(bend_classes(data.labels[:, 1]), minlength=len(BEND_CLASSES)) / len(data)
    assert BEND_CLASSES == ("sharp_left", "left", "straight", "right", "sharp_right")
    assert shares.min() > 0.12 and shares.max() < 0.28, shares


def test_bend_classes_follow_the_turn_command() -> None:
    w = np.array([5.0, 3.0, 2.0, 1.0, 0.0, -1.0, -2.0, -3.0, -5.0])  # w > 0 turns left; ties: the gentler
    assert bend_classes(w).tolist() == [0, 1, 1, 2, 2, 2, 3, 3, 4]
    assert bend_classes(w).dtype == np.int64


def test_groups_cover_every_circuit_evenly(data: DrivingData) -> None:
    assert np.array_equal(np.unique(data.groups), np.arange(N_CIRCUITS))
    assert np.array_equal(np.bincount(data.groups), np.full(N_CIRCUITS, 800 // N_CIRCUITS))


def test_images_show_sky_above_road(data: DrivingData) -> None:
    images = data.images.astype(np.float32)
    assert images.reshape(len(images), -1).std(axis=1).min() > 10.0
    sky, road = images[:, :5].mean(axis=(1, 2)), images[:, -10:, 80:120].mean(axis=(1, 2))
    assert (sky[:, 2] - sky[:, 0]).mean() > 20.0  # sky is blue
    assert np.abs(sky - road).sum(axis=1).min() > 30.0
    assert np.abs(road[:, 2] - road[:, 0]).mean() < 15.0  # asphalt is grey


def test_circuit_is_closed_with_bends_both_ways(circuit: Circuit) -> None:
    np.testing.assert_allclose(_pose(circuit, 0.0), _pose(circuit, circuit.length), atol=1e-6)
    kappa = circuit.curvature(np.linspace(0.0, circuit.length, 2000))
    assert kappa.min() < -1 / 70 and kappa.max() > 1 / 35 and np.abs(kappa).max() < 1 / 15
    assert 7.0 <= circuit.lane_width <= 8.0


def test_locate_recovers_track_coordinates_across_the_road(circuit: Circuit) -> None:
    rng = np.random.default_rng(0)
    half = circuit.lane_width / 2 + circuit.markings.kerb_width
    for s, offset, err in zip(rng.uniform(0, circuit.length, 200), rng.uniform(-half, half, 200),
                              rng.uniform(-0.5, 0.5, 200)):
        where = circuit.locate(_pose(circuit, s, offset, err))
        assert abs((where.s - s + circuit.length / 2) % circuit.length - circuit.length / 2) < 0.05
        assert where.offset == pytest.approx(offset, abs=0.02)
        assert where.heading_error == pytest.approx(err, abs=1e-3)


def test_expert_steers_back_towards_the_centreline(circuit: Circuit) -> None:
    expert, s = ExpertController(), _straightest(circuit)
    _, w_centre = expert.command(circuit, _pose(circuit, s))
    _, w_right = expert.command(circuit, _pose(circuit, s, offset=-1.5))
    _, w_left = expert.command(circuit, _pose(circuit, s, offset=1.5))
    _, w_turned_left = expert.command(circuit, _pose(circuit, s, yaw_error=0.2))
    assert abs(w_centre) < 1.0
    assert w_right > w_centre + 1.0 and w_left < w_centre - 1.0
    assert w_turned_left < w_centre - 1.0
    _, w_reverse = expert.command(circuit, _pose(circuit, s, offset=-1.5, yaw_error=np.pi))
    assert w_reverse < -1.0  # driving the other way, the same spot is left of the car's path


def test_expert_slows_for_bends(circuit: Circuit) -> None:
    expert = ExpertController()
    s = np.arange(0.0, circuit.length, 2.0)
    v = np.array([expert.command(circuit, _pose(circuit, si))[0] for si in s])
    w = np.array([expert.command(circuit, _pose(circuit, si))[1] for si in s])
    bend = np.abs(circuit.curvature(s[:, None] + np.linspace(*expert.preview, 30))).mean(axis=1)
    assert v[np.argmax(bend)] < v[np.argmin(bend)] - 5.0
    assert np.corrcoef(v, bend)[0, 1] < -0.7
    limit = np.sqrt(expert.lateral_accel / np.maximum(bend, 1e-9))
    assert np.all(v <= limit + 1e-6)  # never faster than the bend allows
    assert np.corrcoef(w, circuit.curvature(s + 4.0))[0, 1] > 0.8  # turns with the road


def test_render_responds_to_pose_and_lighting(circuit: Circuit) -> None:
    pose = _pose(circuit, 10.0)
    image = render(circuit, pose)
    assert image.shape == (66, 200, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, render(circuit, pose, Lighting(), Camera()))
    assert np.abs(render(circuit, _pose(circuit, 10.0, 1.5)).astype(int) - image).mean() > 5.0
    dim = render(circuit, pose, Lighting(brightness=0.6))
    assert dim.mean() < 0.75 * image.mean()


def test_ridge_on_tiny_images_predicts_w_on_held_out_circuits(data: DrivingData) -> None:
    n = len(data)
    pixels = data.images[:, 6:, :].astype(np.float32).reshape(n, 10, 6, 25, 8, 3).mean(axis=(2, 4)) / 255
    x = np.hstack([pixels.reshape(n, -1), np.ones((n, 1), np.float32)])
    w = data.labels[:, 1]
    train, test = data.groups < 6, data.groups >= 6
    weights = np.linalg.solve(x[train].T @ x[train] + np.eye(x.shape[1]), x[train].T @ w[train])
    error = np.mean((x[test] @ weights - w[test]) ** 2)
    baseline = np.mean((w[train].mean() - w[test]) ** 2)
    assert error < 0.5 * baseline
