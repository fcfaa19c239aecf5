"""Closed-loop driving simulator: a unicycle driven by raw [v, w] on a circuit (answering through its
response: vehicle.py), a fixed physics step, the front camera rendered from the car's pose at every brain
step; lock-step or real-time clock. Headless, CPU."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .circuit import Pose, Track
from .lap import Checkpoints, LapLog, SimSettings
from .render import Camera, Lighting, render
from .texture import ground_texture
from .vehicle import Car

MODES = ("lock_step", "real_time")


@dataclass(frozen=True)
class Observation:
    """What a brain sees at one brain step: the camera frame, and (for the expert only) the true pose."""

    frame: np.ndarray  # uint8 [rows, cols, 3], the renderer's camera
    pose: Pose


Brain = Callable[[Observation], tuple[float, float]]  # -> raw (v m/s, w)


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
        self.car = Car(x, y, heading, response=self.settings.response,
                       speed_factor=self.settings.speed_factor)
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
        """Physics steps the world runs on the previous command while the brain thinks: in lock-step exactly
        the latency budget (0: the world waits), in real time the measured brain time plus the budget."""
        measured = brain_s if self.settings.mode == "real_time" else 0.0
        return math.ceil((measured + self.settings.latency_budget_s) / self.settings.physics_step_s - 1e-9)

    def _physics(self, ticks: int) -> None:
        dt = self.settings.physics_step_s
        for _ in range(ticks):
            if self.log.stop_reason is not None:
                return
            x0, y0 = self.car.x, self.car.y
            driven = self.car.step(dt)
            self._ticks += 1
            where = self.circuit.locate(self.car.pose)
            finished = self.checkpoints.update(x0, y0, self.car.x, self.car.y)
            self.log.physics_step(self._ticks * dt, self.car.pose, where.offset, driven,
                                  self.checkpoints.completed_pct, finished)
