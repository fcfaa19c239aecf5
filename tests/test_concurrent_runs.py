"""Two `bench-matrix run`s at once on one host, on one store and on two: their cells' timing windows never
overlap (one measuring cell per machine), both finish, and every cell is stored once."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench_matrix.measure.env import host_name
from bench_matrix.measure.machine_lock import LOCK_FILE
from conftest import FAST_SETTINGS, cli, onnx_matrix_text, popen_cli
from lock_helpers import flock_waiters, release, start_holder
from polling import wait_for

pytestmark = pytest.mark.slow

# rounds long enough (the budget's 0.8 s a model: no interval reaches ±0.001 %) that the runs, once both have
# waited for the slot, would go on timing at the same moment
SETTINGS = ("settings: {window_s: 0.05, min_rounds: 4, ci_target: 0.00001, timing_budget_s: 0.4, "
            "warmup_iterations: 2, warmup_s: 0.0, batch_size: 8, timeout_s: 300, processes: 1}\n")
CELLS = {"tiny/fp32", "tiny/fp16", "twin/fp32", "twin/fp16"}  # tiny.onnx twice, through ONNX Runtime


def key(record: dict) -> str:
    return "/".join(record["cell"][k] for k in ("model", "precision"))


def stored(project: Path, workspace: str) -> list[dict]:
    out = cli(project, "--workspace", str(project / workspace), "report", "--format", "json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)["records"]


def run_both(project: Path, first: list[str], second: list[str], locks: str = LOCK_FILE) -> list[str]:
    """Start two runs (sharing one lock directory) while the slot is held, let it go once both wait for it (so
    their timing phases collide, however the machine delayed either) or for another of the `locks` (a glob of
    that directory), and wait for both to finish; their outputs."""
    env = {"BENCH_MATRIX_LOCK_DIR": str(project / "lock")}
    holder = start_holder("the test", env=env)
    runs = [popen_cli(project, *args, env=env) for args in (first, second)]

    def both_waiting() -> bool:
        for proc in runs:
            assert proc.poll() is None, proc.communicate()[0]
        return sum(flock_waiters(lock) for lock in (project / "lock").glob(locks)) == 2

    wait_for(both_waiting, "both runs waiting for the timing slot", timeout_s=300)
    release(holder)
    outputs = [proc.communicate(timeout=600)[0] for proc in runs]
    holder.wait(timeout=60)
    for proc, output in zip(runs, outputs):
        assert proc.returncode == 0, output
    return outputs


def assert_never_overlapping(records: list[dict]) -> None:
    """The spans the ok records' models held the timing slot, in time order, each end before the next starts;
    someone waited (for the other run's rounds: `run_both` has both wait for the slot at once)."""
    held = [tuple(span) for r in records if r["status"] == "ok"
            for span in r["metrics"]["timing_window"]["held"]]
    assert len({r["cell"]["model"] for r in records}) <= len(set(held))  # each model's rounds held it
    windows = sorted(set(held))
    for (_, end), (start, _) in zip(windows, windows[1:]):
        assert end <= start, windows
    assert any(r["metrics"]["timing_window"]["waited_s"] > 0.1 for r in records if r["status"] == "ok")


@pytest.fixture
def project(onnx_project: Path) -> Path:
    text = onnx_matrix_text(["tiny", "twin"], ["fp32", "fp16"])
    (onnx_project / "m.yaml").write_text(text.replace(FAST_SETTINGS, SETTINGS))
    return onnx_project


def test_two_runs_on_one_store_time_one_cell_at_a_time(project: Path):
    run_both(project, ["--workspace", str(project / "ws"), "run", "m.yaml", "--model", "tiny"],
             ["--workspace", str(project / "ws"), "run", "m.yaml", "--model", "twin"])
    records = stored(project, "ws")
    assert sorted(map(key, records)) == sorted(CELLS)  # every cell stored once
    assert all(r["status"] == "ok" for r in records), [r["reason"] for r in records]
    assert_never_overlapping(records)


def test_two_runs_on_two_stores_time_one_cell_at_a_time(project: Path):
    run_both(project, ["--workspace", str(project / "ws1"), "run", "m.yaml"],
             ["--workspace", str(project / "ws2"), "run", "m.yaml"])
    both = []
    for workspace in ("ws1", "ws2"):
        records = stored(project, workspace)
        assert sorted(map(key, records)) == sorted(CELLS) and all(r["status"] == "ok" for r in records)
        both += records
    assert_never_overlapping(both)


def test_two_identical_runs_on_one_store_measure_each_cell_once_and_with_force_both(project: Path):
    """Both have chosen their cells when one waits for the timing slot and the other for the first's store
    lock of the model (without one: for the timing slot too); the second then says the first's are stored."""
    run = ["--workspace", str(project / "ws"), "run", "m.yaml"]
    outputs = run_both(project, run, run, "*.lock")
    assert sum(done(out, "ok") for out in outputs) == len(CELLS)  # each cell measured once
    assert sum(done(out, "already stored") for out in outputs) == len(CELLS)
    meanwhile = "already stored (measured by another run meanwhile)"
    assert sum(out.count(meanwhile) for out in outputs) == len(CELLS)
    assert any("waiting for another run measuring it into" in out for out in outputs)
    assert sorted(map(key, stored(project, "ws"))) == sorted(CELLS)
    forced = run_both(project, *[[*run, "--force", "--model", "tiny"]] * 2)  # tiny's cells, measured by both
    assert [done(out, "ok") for out in forced] == [2, 2] and "already stored (" not in "".join(forced)


def done(output: str, what: str) -> int:
    """A count of the run's closing line, `done: N ok, N skipped, N failed, N already stored`."""
    return int(re.search(rf"(\d+) {what}", output.split("done:")[-1])[1])


def test_job_files_a_killed_run_left_are_swept_by_the_next_and_a_live_processes_stay(project: Path):
    killed = popen_cli(project, "run", "m.yaml", "--model", "tiny")
    jobs = project / "ws" / "jobs"
    wait_for(lambda: list(jobs.rglob("session-*.pickle")), "the run's sessions loading", timeout_s=300)
    killed.kill()  # SIGKILL: nothing of it cleans up; its children end with it
    killed.communicate(timeout=60)
    left = [p for p in jobs.rglob("*") if p.is_file()]
    assert left
    live = left[0].with_name(f"job-{os.getpid()}-1.pickle")  # this test's process, alive: another run's
    live.write_bytes(b"")
    out = cli(project, "run", "m.yaml", "--model", "tiny")
    assert out.returncode == 0, out.stdout + out.stderr
    assert [p for p in jobs.rglob("*") if p.is_file()] == [live]


def test_partial_files_of_an_ended_process_are_swept_by_the_next_run_and_a_live_processes_stay(project: Path):
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                           text=True, check=True)
    dead = int(ended.stdout)  # a conversion killed mid-write: its process is gone
    partials = project / "ws" / "tmp" / host_name()
    stale = [partials / f"partial-{dead}-0-0123abcd", partials / f"partial-{dead}-1-fp32.onnx"]
    (stale[0] / "model").mkdir(parents=True)
    (stale[0] / "model" / "model.onnx").write_bytes(b"\0" * 100)
    stale[1].write_bytes(b"\0" * 100)
    live = partials / f"partial-{os.getpid()}-0-fp32.onnx"  # this test's process, alive: another run's
    live.write_bytes(b"")
    out = cli(project, "run", "m.yaml", "--model", "tiny")
    assert out.returncode == 0, out.stdout + out.stderr
    assert list(partials.iterdir()) == [live]  # the stale ones and the run's own are gone
    beside = [p for p in (project / "ws" / "cache").rglob("*") if "tmp" in p.name or "partial" in p.name]
    assert not beside  # nothing was written in cache/ under a temporary name
