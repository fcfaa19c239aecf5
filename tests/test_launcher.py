"""Child processes: results come back, crashes and timeouts become reasons, phases reach the parent."""

from __future__ import annotations

import time

from pathlib import Path

import pytest

from bench_matrix.errors import UserError
from bench_matrix.executors.process import run_in_process
from launcher_jobs import AbortJob, EchoJob, EnvJob, FailJob, SleepJob


@pytest.fixture(autouse=True)
def tests_importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))


def test_a_job_on_every_core_lets_waiting_openmp_threads_sleep_unless_told_otherwise(tmp_path, monkeypatch):
    """Training on every core beside a busy one: spinning OpenMP threads stalled each step (a PilotNet's
    8 epochs took 254 s instead of 36 s beside one CPU-bound process)."""
    names = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)

    def seen(threads: int | None) -> dict:
        return run_in_process(EnvJob(names), tmp_path / "jobs", tmp_path / "log.txt", 60, threads).result

    assert seen(None)["OMP_WAIT_POLICY"] == "PASSIVE"
    assert seen(1) == {"OMP_WAIT_POLICY": None, "OMP_NUM_THREADS": "1"}  # a measuring process: as the user's
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert seen(None)["OMP_WAIT_POLICY"] == "ACTIVE"


def test_crash_without_result_reports_signal_and_log_tail(tmp_path):
    ended = run_in_process(AbortJob(), tmp_path / "jobs", tmp_path / "log.txt", timeout_s=60)
    assert not ended.ok
    assert "killed by signal SIGABRT" in ended.error
    assert "about to abort" in ended.error and "\n" not in ended.error  # the log's last line


def test_exception_is_reported_with_its_location(tmp_path):
    ended = run_in_process(FailJob(), tmp_path / "jobs", tmp_path / "log.txt", timeout_s=60)
    assert not ended.ok and ended.error.startswith("launcher_jobs: ValueError: bad model")  # where it rose
    assert "\n" not in ended.error and ended.error.endswith(f"(traceback: {tmp_path / 'log.txt'})")
    assert 'File "' in (tmp_path / "log.txt").read_text()  # the traceback is in the log


def test_timeout_kills_the_child(tmp_path):
    begin = time.monotonic()
    phases = []
    ended = run_in_process(SleepJob(60), tmp_path / "jobs", tmp_path / "log.txt",
                           timeout_s=2, on_phase=phases.append)
    assert time.monotonic() - begin < 20  # killed, not left to sleep its 60 s: 10 times the limit's 2 s
    assert "timed out after 2 s (in phase 'measure')" in ended.error
    assert phases == ["measure"]


def test_value_and_phases_come_back(tmp_path):
    phases = []
    ended = run_in_process(EchoJob([1, "a"]), tmp_path / "jobs", tmp_path / "log.txt",
                           timeout_s=60, on_phase=phases.append)
    assert ended.ok and ended.result == [1, "a"]
    assert phases == ["convert", "measure"]
    assert not list((tmp_path / "jobs").iterdir())  # job files are cleaned up



@pytest.mark.parametrize("timeout_s", [float("inf"), 1e30, 10**400])
def test_a_limit_too_long_for_a_timer_waits_as_long_as_needed(tmp_path, timeout_s):
    ended = run_in_process(EchoJob(7), tmp_path / "jobs", tmp_path / "log.txt",
                           timeout_s=timeout_s)
    assert ended.ok and ended.result == 7


@pytest.mark.parametrize("timeout_s", [float("nan"), 0, -1.0])
def test_a_limit_that_is_not_a_positive_number_is_refused_before_starting(tmp_path, timeout_s):
    with pytest.raises(UserError, match=r"a time limit must be a positive number of seconds, got .*"
                                        r"timeout_s"):
        run_in_process(EchoJob(7), tmp_path / "jobs", tmp_path / "log.txt",
                       timeout_s=timeout_s)
    assert not (tmp_path / "jobs").exists()
