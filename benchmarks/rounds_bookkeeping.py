"""The rounds' bookkeeping between windows, as a share of the windows it comes between.

After every round the scheduler judges each live cell (its p50 and speed-up intervals: `narrow`) and the
answers judge every cell's figures so far (`figures`, as the record would have them). That work runs on
the budget's clock, so it is budget not spent timing. This times both on simulated cells (two processes, a
latency and a throughput window a round) at a window of `--window-s` seconds, for fast and slow models and
few and many rounds, and prints the work per cell and round as a share of that cell's windows in the round.

    .venv/bin/python benchmarks/rounds_bookkeeping.py [--window-s 0.1] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_matrix.measure.interference import LIMITS
from bench_matrix.measure.schedule import LATENCY, RoundsSettings, Timed, Window, narrow, spread
from bench_matrix.scenarios.timed import figures


def cell(rng: np.random.Generator, call_ms: float, window_s: float, rounds: int) -> Timed:
    """A simulated cell: `rounds` rounds of 2 processes, each a latency and a throughput window."""
    calls = max(4, int(window_s * 1e3 / call_ms))
    timed = Timed()
    for slot in ((r, j) for r in range(rounds) for j in range(2)):
        timed.add(slot, Window(LATENCY, rng.normal(call_ms, call_ms * 0.01, calls)))
        batches = rng.normal(call_ms * 32, call_ms * 0.3, max(3, calls // 32))
        timed.add(slot, Window("throughput", batches, 32))
    return timed


def per_round_s(timed: Timed, base: Timed, repeats: int) -> float:
    """Seconds of one round's judging of this cell: its narrow() and its figures()."""
    settings, model = RoundsSettings(), spread([timed, base])
    start = time.perf_counter()
    for _ in range(repeats):
        narrow(timed, base, settings, model)
        figures(timed, base, settings, LIMITS, {LATENCY: model})
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--window-s", type=float, default=0.1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'call ms':>8} {'rounds':>6} {'judging ms':>10} {'share of its windows':>21}")
    for call_ms in (1.0, 0.05):
        for rounds in (10, 50):
            base, timed = (cell(rng, call_ms, args.window_s, rounds) for _ in range(2))
            seconds = per_round_s(timed, base, args.repeats)
            windows_s = 2 * 2 * args.window_s  # two processes, a latency and a throughput window each
            print(f"{call_ms:>8} {rounds:>6} {seconds * 1e3:>10.1f} {seconds / windows_s:>20.1%}")


if __name__ == "__main__":
    main()
