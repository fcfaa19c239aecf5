"""Circuits drawn as a turtle draws them: straights and arcs in driving order, two straights' lengths solved
so that the road closes on its start."""

from __future__ import annotations

import math

import numpy as np

Segment = tuple[float, float]  # (radius m, turn degrees: + left) of an arc; (0, length m) of a straight
SPACING = 2.0  # metres between the points laid along each segment


def layout_points(segments: list[Segment]) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Points every SPACING metres along the segments from (0, 0) heading +x, and the final pose."""
    x = y = heading = 0.0
    points = []
    for radius, amount in segments:
        arc = radius > 0
        length = radius * math.radians(abs(amount)) if arc else amount
        steps = max(2 if arc else 1, round(length / SPACING))
        turn = math.radians(amount) / steps if arc else 0.0
        for _ in range(steps):
            points.append((x, y))
            chord = 2 * radius * math.sin(abs(turn) / 2) if arc else length / steps
            x, y = x + chord * math.cos(heading + turn / 2), y + chord * math.sin(heading + turn / 2)
            heading += turn
    return np.array(points), (x, y, math.degrees(heading))


def closed_layout(segments: list[Segment], free: tuple[int, int]) -> np.ndarray:
    """The points of `segments` with the straights at indices `free` lengthened (from the length given) so the
    road ends where it starts; ValueError when it cannot close with them."""
    def end(extra: tuple[float, float]) -> np.ndarray:
        return np.array(layout_points(_lengthen(segments, free, extra))[1][:2])

    start = end((0.0, 0.0))
    effect = np.stack([end((1.0, 0.0)) - start, end((0.0, 1.0)) - start], 1)  # the end moves linearly
    extra = np.linalg.solve(effect, -start)
    if any(segments[i][1] + e <= 0 for i, e in zip(free, extra)):
        raise ValueError(f"the layout cannot close with straights {free}: they would need {extra} m more")
    return layout_points(_lengthen(segments, free, (float(extra[0]), float(extra[1]))))[0]


def _lengthen(segments: list[Segment], free: tuple[int, int], extra: tuple[float, float]) -> list[Segment]:
    shaped = list(segments)
    for index, length in zip(free, extra):
        shaped[index] = (0.0, segments[index][1] + length)
    return shaped
