"""Closed-loop driving simulator: a unicycle driven by raw [v, w] on a circuit, a fixed physics step, the
front camera rendered from the car's pose at every brain step; lock-step or real-time clock. Headless, CPU."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .circuit import Pose, Track
from .expert import V_RANGE, W_RANGE, ExpertController
from .lap import Checkpoints, LapLog, SimSettings
from .render import Camera, Lighting, render
from .texture import ground_texture

MODES = ("lock_step", "real_time")
W_GAIN = ExpertController.w_gain  # w units per 1/m of path curvature: the car's yaw rate is v * w / W_GAIN
V_LIMITS = (0.0, V_RANGE[1])  # the car neither reverses nor exceeds the fastest training label
STOP_REASONS = ("lap_completed", "off_road", "stuck", "time_limit")


@dataclass(frozen=True)
class Observation:
    """What a brain sees at one brain step: the camera frame, and (for the expert only) the true pose."""

    frame: np.ndarray  # uint8 [rows, cols, 3], the renderer's camera
    pose: Pose


Brain = Callable[[Observation], tuple[float, float]]  # -> raw (v m/s, w)


@dataclass
class Car:
    """The vehicle state: pose and the command it is executing."""

    x: float
    y: float
    yaw: float
    v: float = 0.0
    w: float = 0.0

    @property
    def pose(self) -> Pose:
        return self.x, self.y, self.yaw

    def command(self, v: float, w: float) -> None:
        """Take a raw [v, w] command, clipped to what the car can do."""
        self.v = float(np.clip(v, *V_LIMITS))
        self.w = float(np.clip(w, *W_RANGE))

    def advance(self, dt: float) -> float:
        """Move exactly along the arc of constant speed and yaw rate for dt; return the distance driven."""
        rate = self.v * self.w / W_GAIN
        if abs(rate * dt) < 1e-9:
            self.x += self.v * dt * math.cos(self.yaw)
            self.y += self.v * dt * math.sin(self.yaw)
        else:
            turn = self.yaw + rate * dt
            self.x += self.v / rate * (math.sin(turn) - math.sin(self.yaw))
            self.y -= self.v / rate * (math.cos(turn) - math.cos(self.yaw))
            self.yaw = turn
        return self.v * dt


@dataclass
class Simulator:
    """One lap of one brain on one circuit; `run` returns the lap's log for `lap.summarise`."""

    circuit: Track
    settings: SimSettings
    camera: Camera = field(default_factory=Camera)
    lighting: Lighting = field(default_factory=Lighting)

    def __post_init__(self) -> None:
        if self.settings.mode not in MODES:
            raise ValueError(f"mode {self.settings.mode!r}; allowed: {', '.join(MODES)}")
        x, y, heading = (float(v) for v in self.circuit.pose_at(0.0))
        self.car = Car(x, y, heading)
        self.checkpoints = Checkpoints(self.circuit, self.settings.checkpoint_spacing_m)
        self.log = LapLog(self.circuit, self.settings)
        ground_texture(self.circuit)  # rasterised once, before the clock runs
        self._ticks = 0
        self._period = max(1, round(self.settings.brain_period_s / self.settings.physics_step_s))

    def run(self, brain: Brain) -> LapLog:
        """Drive until a stop reason; every brain step renders, asks the brain, then steps the physics."""
        begin = time.perf_counter()
        while self.log.stop_reason is None:
            tick = time.perf_counter()
            frame = render(self.circuit, self.car.pose, self.lighting, self.camera)
            asked = time.perf_counter()
            v, w = brain(Observation(frame, self.car.pose))
            answered = time.perf_counter()
            self.log.brain_step(answered - asked, v, w)
            late = self._late_ticks(answered - asked)
            self._physics(late)
            self.car.command(v, w)
            self._physics(max(self._period - late, 0))
            self.log.overhead(asked - tick + time.perf_counter() - answered)  # render + physics
        self.log.wall_s = time.perf_counter() - begin
        return self.log

    def _late_ticks(self, brain_s: float) -> int:
        """Physics steps the world runs on the previous command while the brain thinks (0 in lock-step)."""
        if self.settings.mode == "lock_step":
            return 0
        return math.ceil((brain_s + self.settings.latency_budget_s) / self.settings.physics_step_s - 1e-9)

    def _physics(self, ticks: int) -> None:
        dt = self.settings.physics_step_s
        for _ in range(ticks):
            if self.log.stop_reason is not None:
                return
            x0, y0 = self.car.x, self.car.y
            driven = self.car.advance(dt)
            self._ticks += 1
            where = self.circuit.locate(self.car.pose)
            finished = self.checkpoints.update(x0, y0, self.car.x, self.car.y)
            self.log.physics_step(self._ticks * dt, self.car.pose, where.offset, driven,
                                  self.checkpoints.completed_pct, finished)
