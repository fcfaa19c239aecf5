"""`bench-matrix device check` without a host (bench_matrix/measure/noise.py): its fields and the width it
states, from injected windows, OS readings and sysfs files; and one short real check of this machine."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench_matrix.measure.interference import CLOCK_TICKS, Reading
from bench_matrix.measure.noise import Rounds, check
from bench_matrix.measure.rounds import t95

MEDIANS = [1.0, 1.02, 0.99, 1.01, 0.97, 1.03, 1.0, 0.98, 1.04, 1.0, 1.01, 0.99]


def sysfs(root: Path, siblings: str) -> Path:
    """Two CPUs whose topology says `siblings` for each, a governor, no boost file."""
    for cpu in (0, 1):
        (root / f"cpu{cpu}" / "topology").mkdir(parents=True)
        (root / f"cpu{cpu}" / "topology" / "thread_siblings_list").write_text(siblings + "\n")
        (root / f"cpu{cpu}" / "cpufreq").mkdir()
        (root / f"cpu{cpu}" / "cpufreq" / "scaling_governor").write_text("performance\n")
    return root


def injected(tmp_path: Path, siblings: str, steal_ticks: int, other_ticks: int):
    """The check over MEDIANS (one clock second a window) with readings that give the steal and load asked."""
    clock, windows = iter(range(100)), iter(MEDIANS)
    readings = iter([Reading(0.0, 0.0, 0, (1,), {0: (0, 0), 1: (0, 0)}),
                     Reading(12.0, 12.0, 5, (1,), {0: (other_ticks, 0), 1: (12 * CLOCK_TICKS, steal_ticks)})])
    loadavg = tmp_path / "loadavg"
    loadavg.write_text("0.50 0.40 0.30 1/100 123\n")
    return check(lambda seconds: next(windows), 9.5, clock=lambda: float(next(clock)),
                 read=lambda: next(readings), sysfs=sysfs(tmp_path / "cpu", siblings), loadavg=loadavg,
                 cpus=(0, 1))


def test_a_quiet_machine_states_its_spread_and_the_width_a_cell_reaches(tmp_path: Path):
    found = injected(tmp_path, "0", 0, 0)
    logs = np.log(MEDIANS)
    spread = 1.4826 * float(np.median(np.abs(logs - np.median(logs))))
    assert len(found.medians_ms) == 12 and found.spread == pytest.approx(spread)
    rounds = 10  # 3 s ÷ (2 × 0.15 s): 10 rounds of 2 processes' latency and half-length throughput windows
    width = t95(rounds - 1) * spread / math.sqrt(2) / math.sqrt(rounds)
    assert found.to_json()["width"]["3"] == pytest.approx(width, abs=1e-6)
    rows = dict(found.rows())
    assert rows["a cell's p50"].startswith(f"±{width:.1%} in 3 s")
    assert rows["CPU steal"] == "0.0%" and rows["other processes"].endswith("load 0.5 0.4 0.3")
    assert rows["frequency"].startswith("governor performance, boost not exposed")
    assert rows["SMT siblings"].startswith("none") and found.verdict() == "quiet"


def test_steal_load_and_smt_siblings_make_it_noisy_and_say_why(tmp_path: Path):
    found = injected(tmp_path, "0-1", steal_ticks=CLOCK_TICKS // 2, other_ticks=6 * CLOCK_TICKS)
    assert found.shared() == [0, 1]
    assert "CPU 0 shares its core with CPU 1" in dict(found.rows())["SMT siblings"]
    verdict = found.verdict()
    assert verdict.startswith("noisy: ") and "CPU steal 4.2%" in verdict
    assert "other processes took 25% of the machine" in verdict


def test_more_budget_narrows_the_width_as_the_square_root_of_the_rounds():
    rounds = Rounds()
    assert rounds.width(0.02, 12.0) < rounds.width(0.02, 3.0) / 1.9
    assert rounds.width(0.02, rounds.budget_for(0.02, 0.005)) <= 0.005


def test_device_check_without_a_host_checks_this_machine():
    done = subprocess.run([sys.executable, "-m", "bench_matrix.cli", "device", "check", "--seconds", "1",
                           "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert found["windows"] >= 3 and found["median_ms"] > 0 and found["verdict"]
    assert all(math.isfinite(w) and w > 0 for w in found["width"].values())
    assert {"steal_share", "machine_share"} <= set(found["interference"]) and found["siblings"]


def test_device_check_refuses_a_bad_duration():
    done = subprocess.run([sys.executable, "-m", "bench_matrix.cli", "device", "check", "--seconds", "0"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--seconds must be more than 0" in done.stderr + done.stdout
