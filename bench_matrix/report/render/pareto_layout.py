"""Where the Pareto chart puts each point's number (greedy: clear of the other numbers and markers) and the
round sizes its size legend shows: pure geometry in display pixels and bytes, for render/plots.py."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from bench_matrix.report.render.columns import MIB

RINGS = 8  # label candidate rings around a point, each one label height further out
ANGLES = tuple(math.radians(a) for a in (0, 180, 90, 270, 30, 150, 330, 210, 60, 120, 300, 240))


@dataclass(frozen=True)
class Box:
    """An axis-aligned rectangle (display pixels, y up)."""

    x0: float
    y0: float
    x1: float
    y1: float

    def overlaps(self, other: Box) -> bool:
        return self.x0 < other.x1 and other.x0 < self.x1 and self.y0 < other.y1 and other.y0 < self.y1

    def within(self, bounds: Box) -> bool:
        return bounds.x0 <= self.x0 and self.x1 <= bounds.x1 and bounds.y0 <= self.y0 and self.y1 <= bounds.y1

    def distance(self, x: float, y: float) -> float:
        """From (x, y) to the nearest point of the box (0 inside)."""
        return math.hypot(max(self.x0 - x, 0.0, x - self.x1), max(self.y0 - y, 0.0, y - self.y1))

    def hits_circle(self, x: float, y: float, radius: float) -> bool:
        return self.distance(x, y) < radius


def reference_sizes(sizes: Sequence[float]) -> list[float]:
    """Two or three round sizes in bytes (1, 2, 5 × 10^k MiB) spanning `sizes`, for the size legend."""
    low, high = min(sizes) / MIB, max(sizes) / MIB
    steps = [m * 10.0**k for k in range(-4, 7) for m in (1, 2, 5)]
    inside = [s for s in steps if low <= s <= high]
    if len(inside) > 3:
        inside = [inside[0], inside[len(inside) // 2], inside[-1]]
    if not inside:
        inside = [float(f"{high:.2g}")]
    return [s * MIB for s in inside]


def place_labels(anchors: Sequence[tuple[float, float]], radii: Sequence[float],
                 sizes: Sequence[tuple[float, float]], bounds: Box, gap: float) -> list[tuple[float, float]]:
    """Each label's (w, h) centre beside its marker (`anchors[i]`, radius `radii[i]`), in order: the nearest
    spot in `bounds` clear of placed labels and other markers, else the one with the fewest collisions."""
    placed: list[Box] = []
    for i, ((x, y), radius, size) in enumerate(zip(anchors, radii, sizes)):
        others = [(ax, ay, r) for j, ((ax, ay), r) in enumerate(zip(anchors, radii)) if j != i]
        candidates = [_candidate(x, y, radius + gap + ring * size[1], angle, size)
                      for ring in range(RINGS) for angle in ANGLES]
        placed.append(_first_clear(candidates, lambda box: _collisions(box, placed, others, bounds)))
    return [((b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2) for b in placed]


def _first_clear(candidates: list[Box], collisions: Callable[[Box], tuple[bool, int, int]]) -> Box:
    """The first candidate without collisions, else the one with the fewest (the first of equals)."""
    best, best_key = candidates[0], collisions(candidates[0])
    for box in candidates:
        key = collisions(box)
        if key == (False, 0, 0):
            return box
        if key < best_key:
            best, best_key = box, key
    return best


def _candidate(x: float, y: float, distance: float, angle: float, size: tuple[float, float]) -> Box:
    """The label box whose corner (or edge) nearest the point lies `distance` from it in direction `angle`."""
    cos, sin = math.cos(angle), math.sin(angle)
    sx = 0.0 if abs(cos) < 1e-9 else math.copysign(1.0, cos)
    sy = 0.0 if abs(sin) < 1e-9 else math.copysign(1.0, sin)
    cx, cy = x + cos * distance + sx * size[0] / 2, y + sin * distance + sy * size[1] / 2
    return Box(cx - size[0] / 2, cy - size[1] / 2, cx + size[0] / 2, cy + size[1] / 2)


def _collisions(box: Box, placed: list[Box], markers: list[tuple[float, float, float]], bounds: Box
                ) -> tuple[bool, int, int]:
    """How bad a candidate is: outside the bounds, then labels hit, then markers hit."""
    return (not box.within(bounds), sum(box.overlaps(other) for other in placed),
            sum(box.hits_circle(x, y, r) for x, y, r in markers))
