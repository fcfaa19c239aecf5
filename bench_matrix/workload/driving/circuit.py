"""Procedural closed circuits: arc-length centreline, curvature and pose localisation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_ORDERS = np.array([2, 3, 4, 5])
_MAX_AMPLITUDES = np.array([0.20, 0.13, 0.08, 0.05])
_MAX_CURVATURE = 1.0 / 18.0  # tightest bend: 18 m radius
_MIN_RIGHT_CURVATURE = 1.0 / 70.0  # at least one right bend of radius <= 70 m
_MIN_LEFT_CURVATURE = 1.0 / 35.0  # at least one left bend of radius <= 35 m
_CLEARANCE = 6.0  # grass between distinct parts of the track, metres
GRID_STEP = 0.25  # spacing of the dense centreline used for localisation, metres

Pose = tuple[float, float, float]  # world x, y (metres) and yaw (radians, counter-clockwise from +x)


@dataclass(frozen=True)
class Markings:
    """Painted markings and kerbs, in metres; the road spans |d| <= lane_width / 2."""

    edge_inset: float = 0.25
    edge_width: float = 0.18
    centre_width: float = 0.15
    dash_length: float = 3.0
    dash_gap: float = 3.0
    kerb_width: float = 0.8
    kerb_stripe: float = 1.2
    centre_yellow: bool = True


@dataclass(frozen=True, eq=False)
class RadialProfile:
    """Closed polar curve r(t) = R0 (1 + sum_k a_k cos(k t + phi_k))."""

    base_radius: float
    amplitudes: np.ndarray
    phases: np.ndarray

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return r, dr/dt and d2r/dt2 at polar angles t."""
        arg = np.multiply.outer(t, _ORDERS) + self.phases
        cos, sin = np.cos(arg), np.sin(arg)
        a = self.amplitudes * self.base_radius
        return self.base_radius + cos @ a, -sin @ (a * _ORDERS), -cos @ (a * _ORDERS**2)


@dataclass(frozen=True)
class TrackPosition:
    """A pose expressed relative to the centreline (forward = counter-clockwise)."""

    s: float  # arc length of the nearest centreline point, metres
    offset: float  # signed lateral offset, positive to the left of the centreline
    heading_error: float  # pose yaw minus centreline heading, wrapped to [-pi, pi)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _curve(profile: RadialProfile, t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Centre x, y, heading, curvature and ds/dt at polar angles t."""
    r, dr, ddr = profile.evaluate(t)
    cos, sin = np.cos(t), np.sin(t)
    tx, ty = dr * cos - r * sin, dr * sin + r * cos
    speed = np.hypot(r, dr)
    kappa = (r * r + 2 * dr * dr - r * ddr) / speed**3
    return r * cos, r * sin, np.arctan2(ty, tx), kappa, speed


def _acceptable(profile: RadialProfile, reach: float) -> bool:
    """True when the bends are drivable, both directions of bend exist and the road never overlaps."""
    t = np.linspace(0.0, 2 * np.pi, 4096, endpoint=False)
    x, y, _, kappa, speed = _curve(profile, t)
    if np.abs(kappa).max() > _MAX_CURVATURE or kappa.min() > -_MIN_RIGHT_CURVATURE or kappa.max() < _MIN_LEFT_CURVATURE:
        return False
    s = np.cumsum(speed) * (t[1] - t[0])
    keep = np.searchsorted(s, np.arange(0.0, s[-1], 2.0))
    pts, sk = np.stack([x[keep], y[keep]], 1), s[keep]
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    arc = np.abs(sk[:, None] - sk[None])
    arc = np.minimum(arc, s[-1] - arc)
    return bool(dist[arc > 30.0].min(initial=np.inf) > 2 * reach + _CLEARANCE)


class Track:
    """A closed road around an arc-length centreline; subclasses set `length`, `lane_width`, `markings`,
    `seed` and the localisation grid, and implement `pose_at` and `curvature`."""

    seed: int
    lane_width: float
    markings: Markings
    length: float
    _grid: np.ndarray  # [2, n] centreline x, y every GRID_STEP metres
    _grid_heading: np.ndarray

    def pose_at(
        self, s: np.ndarray | float, offset: np.ndarray | float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y and centreline heading at arc length s, shifted `offset` metres to the left."""
        raise NotImplementedError

    def curvature(self, s: np.ndarray | float) -> np.ndarray:
        """Signed centreline curvature (1/m, positive = left bend when driving forward) at s."""
        raise NotImplementedError

    def _build_grid(self) -> None:
        """The dense centreline the localisation searches, every GRID_STEP metres."""
        x, y, self._grid_heading = self.pose_at(np.arange(0.0, self.length, GRID_STEP))
        self._grid = np.stack([x, y])

    def locate(self, pose: Pose) -> TrackPosition:
        """Nearest centreline point, signed lateral offset and heading error of a pose."""
        x, y, yaw = pose
        i = int(np.argmin((self._grid[0] - x) ** 2 + (self._grid[1] - y) ** 2))
        (cx, cy), heading = self._grid[:, i], self._grid_heading[i]
        s = i * GRID_STEP + (x - cx) * np.cos(heading) + (y - cy) * np.sin(heading)
        cx, cy, heading = (float(v) for v in self.pose_at(s))
        offset = -(x - cx) * np.sin(heading) + (y - cy) * np.cos(heading)
        return TrackPosition(float(s % self.length), float(offset), float(wrap_angle(yaw - heading)))


@dataclass(eq=False)
class Circuit(Track):
    """A closed, non-self-intersecting procedural circuit with an arc-length centreline."""

    seed: int
    profile: RadialProfile
    lane_width: float
    markings: Markings
    length: float = field(init=False)
    _s_knots: np.ndarray = field(init=False, repr=False)
    _t_knots: np.ndarray = field(init=False, repr=False)
    _grid: np.ndarray = field(init=False, repr=False)
    _grid_heading: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        """Build the arc-length parametrisation and the dense localisation grid."""
        t = np.linspace(0.0, 2 * np.pi, 16385)
        speed = _curve(self.profile, t)[4]
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
        self._s_knots, self._t_knots, self.length = s, t, float(s[-1])
        self._build_grid()

    @classmethod
    def from_seed(cls, seed: int, max_tries: int = 500) -> Circuit:
        """Draw a random circuit deterministically from `seed` (rejection-sampled)."""
        rng = np.random.default_rng(seed)
        lane_width = float(rng.uniform(7.0, 8.0))
        markings = Markings(centre_yellow=bool(rng.random() < 0.5))
        for _ in range(max_tries):
            profile = RadialProfile(
                base_radius=float(rng.uniform(55.0, 75.0)),
                amplitudes=rng.uniform(0.3, 1.0, len(_ORDERS)) * _MAX_AMPLITUDES,
                phases=rng.uniform(0.0, 2 * np.pi, len(_ORDERS)),
            )
            if _acceptable(profile, lane_width / 2 + markings.kerb_width):
                return cls(int(seed), profile, lane_width, markings)
        raise RuntimeError(f"no acceptable circuit for seed {seed} in {max_tries} tries")

    def _angle(self, s: np.ndarray | float) -> np.ndarray:
        """Polar angle of the centreline point at arc length s (periodic)."""
        return np.interp(np.mod(s, self.length), self._s_knots, self._t_knots)

    def pose_at(
        self, s: np.ndarray | float, offset: np.ndarray | float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y and centreline heading at arc length s, shifted `offset` metres to the left."""
        x, y, heading, _, _ = _curve(self.profile, self._angle(s))
        return x - offset * np.sin(heading), y + offset * np.cos(heading), heading

    def curvature(self, s: np.ndarray | float) -> np.ndarray:
        """Signed centreline curvature (1/m, positive = left bend when driving forward) at s."""
        return _curve(self.profile, self._angle(s))[3]
