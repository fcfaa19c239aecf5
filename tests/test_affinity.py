"""Pinning the measuring process to `threads` CPUs (in child processes: pytest itself stays unpinned), and the
CPU frequency state read from sysfs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench_matrix.measure import env
from bench_matrix.measure.affinity import NOT_EXPOSED, SYSFS_CPU, cpu_frequency_state, pin_threads, spread

ALLOWED = sorted(os.sched_getaffinity(0))
PIN = """
import json, os, sys, threading
from bench_matrix.measure import env
from bench_matrix.measure.affinity import pin_threads
stop = threading.Event()
before = threading.Thread(target=stop.wait)
before.start()
chosen = pin_threads(int(sys.argv[1]))
after = threading.Thread(target=stop.wait)
after.start()
masks = {name: sorted(os.sched_getaffinity(t.native_id))
         for name, t in (("before", before), ("after", after))}
stop.set()
print(json.dumps({"chosen": chosen, "main": sorted(os.sched_getaffinity(0)), **masks,
                  "cores_usable": env.capture()["cores_usable"]}))
"""


def pinned(threads: int, cpus: list[int] | None = None) -> dict:
    """pin_threads(threads) in a fresh process, started on `cpus` (default: ours)."""
    start_on = None if cpus is None else (lambda: os.sched_setaffinity(0, cpus))
    out = subprocess.run([sys.executable, "-c", PIN, str(threads)], capture_output=True, text=True,
                         check=True, preexec_fn=start_on).stdout
    return json.loads(out)


def distinct_cores(cpus: list[int]) -> bool:
    cores = {(SYSFS_CPU / f"cpu{c}/topology/core_id").read_text() for c in cpus}
    return len(cores) == len(cpus)


@pytest.mark.skipif(len(ALLOWED) < 2, reason="needs 2 usable CPUs")
def test_one_thread_is_pinned_to_one_cpu_threads_old_and_new_included():
    result = pinned(1)
    assert len(result["chosen"]) == 1 and result["chosen"][0] in ALLOWED
    assert result["main"] == result["before"] == result["after"] == result["chosen"]
    assert result["cores_usable"] == len(ALLOWED)  # the environment keeps what the process was allowed
    if distinct_cores(ALLOWED):
        assert result["chosen"] == [max(ALLOWED)]  # not CPU 0 when another is allowed


@pytest.mark.parametrize("extra", [0, 3])
def test_as_many_threads_as_cpus_or_more_keeps_every_allowed_cpu(extra):
    result = pinned(len(ALLOWED) + extra)
    assert result["chosen"] == result["main"] == result["after"] == ALLOWED


def test_never_more_cpus_than_allowed():
    result = pinned(2, cpus=[ALLOWED[0]])
    assert result["chosen"] == result["main"] == [ALLOWED[0]]
    assert result["cores_usable"] == 1


def test_a_thread_count_below_one_is_refused():
    with pytest.raises(ValueError, match="threads must be at least 1, got 0"):
        pin_threads(0)


def test_threads_spread_over_physical_cores_before_smt_siblings():
    core_of = {0: (0, 0), 1: (0, 1), 2: (0, 0), 3: (0, 1)}  # 2 cores, 2 hardware threads each
    order = spread((0, 1, 2, 3), core_of)
    assert order == [3, 2, 1, 0]
    assert {core_of[c] for c in order[:2]} == {(0, 0), (0, 1)}
    assert spread((5, 7), {5: (1, 0), 7: (-1, 7)}) == [7, 5]


def test_frequency_state_on_this_machine():
    state = cpu_frequency_state()
    governors = sorted(SYSFS_CPU.glob("cpu[0-9]*/cpufreq/scaling_governor"))
    if governors:
        assert isinstance(state["scaling_governor"], dict)
        assert len(state["scaling_governor"]) >= len(governors)
    else:
        assert state["scaling_governor"] == NOT_EXPOSED and state["scaling_driver"] == NOT_EXPOSED
    boost = SYSFS_CPU / "cpufreq" / "boost"
    assert state["boost"] == (boost.read_text().strip() if boost.is_file() else NOT_EXPOSED)
    assert env.capture()["cpu_frequency"] == state


def test_frequency_state_from_a_sysfs_tree(tmp_path: Path):
    for cpu, governor in ((0, "performance"), (10, "powersave"), (2, None)):
        (tmp_path / f"cpu{cpu}").mkdir()
        if governor:
            (tmp_path / f"cpu{cpu}/cpufreq").mkdir()
            (tmp_path / f"cpu{cpu}/cpufreq/scaling_governor").write_text(f"{governor}\n")
            (tmp_path / f"cpu{cpu}/cpufreq/scaling_driver").write_text("intel_pstate\n")
    (tmp_path / "cpuidle").mkdir()
    (tmp_path / "intel_pstate").mkdir()
    (tmp_path / "intel_pstate/no_turbo").write_text("1\n")
    state = cpu_frequency_state(tmp_path)
    assert state == {"scaling_driver": "intel_pstate",
                     "scaling_governor": {"0": "performance", "2": NOT_EXPOSED, "10": "powersave"},
                     "boost": NOT_EXPOSED, "intel_no_turbo": "1"}
    assert list(state["scaling_governor"]) == ["0", "2", "10"]  # numeric order
    assert cpu_frequency_state(tmp_path / "missing") == {
        "scaling_driver": NOT_EXPOSED, "scaling_governor": NOT_EXPOSED, "boost": NOT_EXPOSED,
        "intel_no_turbo": NOT_EXPOSED}
