"""A circuit given as a closed list of points: a periodic cubic spline through them, with an arc-length
centreline and the same interface as the procedural `Circuit`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .circuit import Markings, Track

MIN_POINTS = 4
MIN_SPACING = 0.5  # metres between consecutive points
MIN_LENGTH = 60.0  # metres of centreline
MIN_RADIUS = 15.0  # tightest bend the car follows comfortably (its own limit is about 9.9 m)
MAX_COORDINATE = 100_000.0  # metres
_DENSE = 0.05  # parameter step of the arc-length table, metres of chord
_FAR_ARC = 30.0  # parts of the centreline this far apart along the road must not touch


class PointCircuit(Track):
    """A closed road through `points` (driven in their order) of width `lane_width`."""

    def __init__(self, points: Sequence[Sequence[float]], lane_width: float = 7.5, seed: int = 0,
                 markings: Markings = Markings()):
        pts = np.asarray(points, dtype=np.float64)
        if problem := shape_problem(pts):
            raise ValueError(problem)
        self.points, self.lane_width, self.seed, self.markings = pts, float(lane_width), int(seed), markings
        chord = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
        self._t = np.concatenate([[0.0], np.cumsum(chord)])  # knot parameters, last = period
        closed = np.vstack([pts, pts[:1]])
        self._xy = closed
        self._m = np.stack([_second_derivatives(self._t, closed[:, k]) for k in range(2)], axis=1)
        t = np.linspace(0.0, self._t[-1], int(np.ceil(self._t[-1] / _DENSE)) + 1)
        speed = np.hypot(*self._derivatives(t, 1))
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
        self._s_knots, self._t_knots, self.length = s, t, float(s[-1])
        self._build_grid()

    def _derivatives(self, t: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
        """x and y (order 0) or their first or second derivative along the spline parameter t."""
        knots = self._t
        i = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
        h = (knots[i + 1] - knots[i])[:, None]
        a, b = (knots[i + 1] - t)[:, None], (t - knots[i])[:, None]
        m0, m1, y0, y1 = self._m[i], self._m[i + 1], self._xy[i], self._xy[i + 1]
        if order == 0:
            value = (m0 * a**3 + m1 * b**3) / (6 * h) + (y0 / h - m0 * h / 6) * a + (y1 / h - m1 * h / 6) * b
        elif order == 1:
            value = (m1 * b**2 - m0 * a**2) / (2 * h) + (y1 - y0) / h - (m1 - m0) * h / 6
        else:
            value = (m0 * a + m1 * b) / h
        return value[:, 0], value[:, 1]

    def _parameter(self, s: np.ndarray | float) -> np.ndarray:
        return np.interp(np.mod(np.atleast_1d(np.asarray(s, dtype=np.float64)), self.length),
                         self._s_knots, self._t_knots)

    def pose_at(
        self, s: np.ndarray | float, offset: np.ndarray | float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y and centreline heading at arc length s, shifted `offset` metres to the left."""
        t = self._parameter(s)
        (x, y), (dx, dy) = self._derivatives(t, 0), self._derivatives(t, 1)
        heading = np.arctan2(dy, dx)
        x, y = x - offset * np.sin(heading), y + offset * np.cos(heading)
        return (x, y, heading) if np.ndim(s) else (x[0], y[0], heading[0])

    def curvature(self, s: np.ndarray | float) -> np.ndarray:
        """Signed centreline curvature (1/m, positive = left bend when driving forward) at s."""
        t = self._parameter(s)
        (dx, dy), (ddx, ddy) = self._derivatives(t, 1), self._derivatives(t, 2)
        kappa = (dx * ddy - dy * ddx) / np.hypot(dx, dy) ** 3
        return kappa if np.ndim(s) else kappa[0]

    def road_problem(self) -> str | None:
        """Why this road cannot be driven (too short, too tight a bend, overlapping itself), or None."""
        if self.length < MIN_LENGTH:
            return f"the circuit is {self.length:.0f} m long; give at least {MIN_LENGTH:.0f} m"
        s = np.arange(0.0, self.length, 1.0)
        kappa = np.abs(self.curvature(s))
        if kappa.max() > 1 / MIN_RADIUS:
            at = s[int(np.argmax(kappa))]
            return (f"its tightest bend has a radius of {1 / kappa.max():.1f} m ({at:.0f} m along the road); "
                    f"bends need a radius of at least {MIN_RADIUS:.0f} m: add points or spread them out")
        x, y, _ = self.pose_at(s)
        gap = np.hypot(x[:, None] - x[None], y[:, None] - y[None])
        arc = np.abs(s[:, None] - s[None])
        arc = np.minimum(arc, self.length - arc)
        touching = (arc > _FAR_ARC) & (gap < self.lane_width + 2 * self.markings.kerb_width)
        if touching.any():
            i, j = np.argwhere(touching)[0]
            return (f"the road touches itself between {s[i]:.0f} m and {s[j]:.0f} m along it "
                    f"(near x={x[i]:.0f}, y={y[i]:.0f}); move those parts apart")
        return None


def shape_problem(points: np.ndarray) -> str | None:
    """Why an array cannot be a circuit's points (shape, count, finiteness, spacing), or None."""
    if points.ndim != 2 or points.shape[1] != 2:
        return "give the points as a list of [x, y] pairs in metres"
    if len(points) < MIN_POINTS:
        return f"give at least {MIN_POINTS} points; got {len(points)}"
    if not np.isfinite(points).all() or np.abs(points).max() > MAX_COORDINATE:
        return f"every coordinate must be a finite number of metres within ±{MAX_COORDINATE:.0f}"
    spacing = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    if spacing.min() < MIN_SPACING:
        k = int(np.argmin(spacing))
        return (f"points {k} and {(k + 1) % len(points)} are {spacing[k]:.2f} m apart; consecutive points "
                f"(the last and the first included) must be at least {MIN_SPACING} m apart")
    return None


def _second_derivatives(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots of the periodic cubic spline through (t, y) (y[-1] == y[0])."""
    h = np.diff(t)
    n = len(h)
    system = np.zeros((n, n))
    rhs = np.empty(n)
    for i in range(n):
        before = (i - 1) % n
        system[i, before] += h[before]
        system[i, i] += 2 * (h[before] + h[i])
        system[i, (i + 1) % n] += h[i]
        rhs[i] = 6 * ((y[i + 1] - y[i]) / h[i] - (y[i] - y[i - 1 if i else n - 1]) / h[before])
    m = np.linalg.solve(system, rhs)
    return np.append(m, m[0])
