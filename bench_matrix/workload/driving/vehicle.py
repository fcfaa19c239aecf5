"""The simulated car: a unicycle whose speed and turn follow the command through optional first-order lags,
commands reaching it after an optional actuation delay (docs/closed-loop.md, "Vehicle")."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .circuit import Pose
from .expert import V_RANGE, W_RANGE, ExpertController

W_GAIN = ExpertController.w_gain  # w units per 1/m of path curvature: the car's yaw rate is v * w / W_GAIN
V_LIMITS = (0.0, V_RANGE[1])  # the car neither reverses nor exceeds the fastest training label


@dataclass(frozen=True)
class Response:
    """How the car answers its commands: time constants of its turn (steering) and speed, and the dead time
    before a command reaches the actuators, in seconds; all 0 is the ideal car that answers at once."""

    steering_tau_s: float = 0.0
    speed_tau_s: float = 0.0
    actuation_delay_s: float = 0.0
    grip_mps2: float = 0.0  # the largest lateral acceleration the tyres hold (beyond it the car runs wide)

    def as_record(self) -> dict[str, float]:
        """The response as the matrix and the records give it: times in milliseconds."""
        return {"steering_tau_ms": self.steering_tau_s * 1e3, "speed_tau_ms": self.speed_tau_s * 1e3,
                "actuation_delay_ms": self.actuation_delay_s * 1e3, "grip_mps2": self.grip_mps2}


IDEAL = Response()
# A 1:10 robot car (docs/closed-loop.md): a servo turning 60 degrees in 0.16 s and F1TENTH's 3.2 rad/s
# steering rate limit; a motor reaching a new speed in about a second (F1TENTH's 9.51 m/s^2 at most); a
# 50 Hz servo frame; tyres holding 1.05 g (F1TENTH's friction coefficient)
SMALL_ROBOT = Response(steering_tau_s=0.1, speed_tau_s=0.5, actuation_delay_s=0.02, grip_mps2=10.3)


@dataclass
class Car:
    """The vehicle state: pose, the speed and turn it executes, and the command they follow."""

    x: float
    y: float
    yaw: float
    v: float = 0.0
    w: float = 0.0
    response: Response = IDEAL
    speed_factor: float = 1.0  # the commanded speed is multiplied by this (a speed margin's probe)
    target: tuple[float, float] = (0.0, 0.0)
    _pending: deque[tuple[float, float, float]] = field(default_factory=deque)  # (due time, v, w)
    _clock: float = 0.0

    @property
    def pose(self) -> Pose:
        return self.x, self.y, self.yaw

    def command(self, v: float, w: float) -> None:
        """Take a raw [v, w] command, clipped to what the car can do; it reaches the actuators after the
        response's actuation delay."""
        v = float(np.clip(v, *V_LIMITS)) * self.speed_factor
        self._pending.append((self._clock + self.response.actuation_delay_s - 1e-9, v,
                              float(np.clip(w, *W_RANGE))))

    def step(self, dt: float) -> float:
        """Apply the commands now due, let speed and turn follow them for dt, then drive; the distance."""
        while self._pending and self._pending[0][0] <= self._clock:
            _, *target = self._pending.popleft()
            self.target = (target[0], target[1])
        self.v = _follow(self.v, self.target[0], self.response.speed_tau_s, dt)
        self.w = _follow(self.w, self.target[1], self.response.steering_tau_s, dt)
        self._clock += dt
        return self.advance(dt)

    def advance(self, dt: float) -> float:
        """Move exactly along the arc of constant speed and yaw rate for dt; return the distance driven."""
        rate = self.v * self.w / W_GAIN
        if self.response.grip_mps2 > 0 and self.v > 0:
            rate = float(np.clip(rate, -self.response.grip_mps2 / self.v, self.response.grip_mps2 / self.v))
        if abs(rate * dt) < 1e-9:
            self.x += self.v * dt * math.cos(self.yaw)
            self.y += self.v * dt * math.sin(self.yaw)
        else:
            turn = self.yaw + rate * dt
            self.x += self.v / rate * (math.sin(turn) - math.sin(self.yaw))
            self.y -= self.v / rate * (math.cos(turn) - math.cos(self.yaw))
            self.yaw = turn
        return self.v * dt


def _follow(value: float, target: float, tau: float, dt: float) -> float:
    """One step of dt of a first-order response with time constant tau towards target (tau 0: at once)."""
    return target if tau <= 0 else target + (value - target) * math.exp(-dt / tau)
