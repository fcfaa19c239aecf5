"""Geometric expert driver: pure-pursuit steering and curvature-limited speed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .circuit import Circuit, Pose

V_RANGE = (6.5, 24.0)  # speed label range of the reference study
W_RANGE = (-7.1, 7.1)  # turn-command label range of the reference study


@dataclass(frozen=True)
class ExpertController:
    """Steers toward a centreline point `lookahead` metres ahead; its speed keeps lateral acceleration bounded."""

    lookahead: float = 9.0  # metres of arc ahead of the nearest centreline point
    w_gain: float = 70.0  # w label units per 1/m of commanded path curvature
    preview: tuple[float, float] = (3.0, 20.0)  # arc window ahead whose mean |curvature| limits speed, metres
    lateral_accel: float = 3.9  # m/s^2 allowed on the commanded path and on the bend ahead

    def command(self, circuit: Circuit, pose: Pose) -> tuple[float, float]:
        """Return the clipped (v, w) command for a car at pose (x, y, yaw) on the circuit."""
        x, y, yaw = pose
        where = circuit.locate(pose)
        direction = 1.0 if np.cos(where.heading_error) >= 0 else -1.0

        tx, ty, _ = circuit.pose_at(where.s + direction * self.lookahead)
        dx, dy = float(tx) - x, float(ty) - y
        ahead = dx * np.cos(yaw) + dy * np.sin(yaw)
        left = -dx * np.sin(yaw) + dy * np.cos(yaw)
        path_curvature = 2.0 * left / (ahead**2 + left**2)
        w = float(np.clip(self.w_gain * path_curvature, *W_RANGE))

        window = where.s + direction * np.linspace(*self.preview, 30)
        bend = max(float(np.abs(circuit.curvature(window)).mean()), abs(path_curvature), 1e-9)
        v = float(np.clip(np.sqrt(self.lateral_accel / bend), *V_RANGE))
        return v, w
