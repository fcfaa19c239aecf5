"""Simulator overhead per brain step: rendering the camera frame plus the physics steps until the next brain
step (5 steps of 10 ms at the default 50 ms period), without any model.

The expert drives one lap of every built-in circuit in lock-step mode (its command is computed from the true
pose and is not counted); the simulator times render and physics of each brain step itself (the figure stored
as `sim_overhead_ms` with every lap). The texture is rasterised before the clock starts. Prints mean, p50 and
p99 per circuit and over all steps; target: mean under 2 ms.

    .venv/bin/python benchmarks/simulator_overhead.py [--laps 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_matrix.workload.driving import ExpertController
from bench_matrix.workload.driving.circuits import BUILTIN_CIRCUITS, builtin_circuit, default_time_limit
from bench_matrix.workload.driving.render import render
from bench_matrix.workload.driving.simulator import SimSettings, Simulator

TARGET_MS = 2.0


def lap_overheads(name: str) -> tuple[np.ndarray, str]:
    """Per brain step render + physics seconds of one expert lap, and how the lap ended."""
    circuit, expert = builtin_circuit(name), ExpertController()
    simulator = Simulator(circuit, SimSettings(time_limit_s=default_time_limit(circuit)))
    log = simulator.run(lambda observation: expert.command(circuit, observation.pose))
    return np.asarray(log.overhead_s), str(log.stop_reason)


def render_only(name: str, frames: int = 200) -> float:
    """Mean seconds of one render alone, at poses spread around the circuit."""
    circuit = builtin_circuit(name)
    x, y, heading = circuit.pose_at(np.linspace(0.0, circuit.length, frames, endpoint=False))
    render(circuit, (float(x[0]), float(y[0]), float(heading[0])))  # texture built outside the clock
    begin = time.perf_counter()
    for pose in zip(x.tolist(), y.tolist(), heading.tolist()):
        render(circuit, pose)
    return (time.perf_counter() - begin) / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--laps", type=int, default=3, help="laps per circuit")
    args = parser.parse_args()
    everything = []
    print(f"{'circuit':8} {'steps':>6} {'mean ms':>8} {'p50 ms':>7} {'p99 ms':>7} {'render ms':>9}  stop")
    for name in BUILTIN_CIRCUITS:
        laps = [lap_overheads(name) for _ in range(args.laps)]
        steps = np.concatenate([overheads for overheads, _ in laps]) * 1e3
        everything.append(steps)
        p50, p99 = np.percentile(steps, [50, 99])
        print(f"{name:8} {len(steps):6d} {steps.mean():8.3f} {p50:7.3f} {p99:7.3f} "
              f"{render_only(name) * 1e3:9.3f}  {', '.join(sorted({stop for _, stop in laps}))}")
    steps = np.concatenate(everything)
    p50, p99 = np.percentile(steps, [50, 99])
    verdict = "meets" if steps.mean() < TARGET_MS else "MISSES"
    print(f"{'all':8} {len(steps):6d} {steps.mean():8.3f} {p50:7.3f} {p99:7.3f}  -> mean {verdict} the "
          f"{TARGET_MS:.0f} ms target")


if __name__ == "__main__":
    main()
