"""The machine's timing slot: one holder at a time across processes, a killed holder frees it at once, waiting
runs name the live holder (never a stale one), and a job's time limit does not count its wait."""

from __future__ import annotations

import getpass
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from bench_matrix.errors import UserError
from bench_matrix.executors.process import run_in_process
from bench_matrix.measure import machine_lock
from bench_matrix.measure.machine_lock import current_holder, timing_slot, waiting_message
from lock_helpers import SlotJob, flock_waiters, release, start_holder
from polling import wait_for

TESTS = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private lock directory (not the host's), seen by this process and the children it starts."""
    directory = tmp_path / "lock"
    monkeypatch.setenv(machine_lock.LOCK_DIR_VARIABLE, str(directory))
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    return directory


def finish(proc: subprocess.Popen) -> dict:
    """The JSON line of a holder, once it has let go (when its time is up or it is told: not told here)."""
    assert proc.wait(timeout=60) == 0 and proc.stdout is not None
    return json.loads(proc.stdout.read().strip().splitlines()[-1])


def test_two_processes_never_hold_the_slot_at_once_and_the_second_names_the_first(lock_dir):
    first = start_holder("matrix.yaml · pilotnet · onnxruntime none fp32")
    second = subprocess.Popen([sys.executable, str(TESTS / "lock_helpers.py"), "second run", "0.1"],
                              stdout=subprocess.PIPE, text=True)
    wait_for(lambda: flock_waiters(lock_dir / machine_lock.LOCK_FILE) == 1, "the second process waiting")
    release(first, after_s=1.1)  # the second waits longer than a second, however slowly it started
    a, b = finish(first), finish(second)
    assert a["window"]["end"] <= b["window"]["start"]
    assert a["window"]["start"] < a["window"]["end"] and b["window"]["start"] < b["window"]["end"]
    assert a["messages"] == [] and a["window"]["waited_s"] == 0
    assert b["window"]["waited_s"] > 1.0
    assert b["messages"] == [f"waiting for the timing phase of pid {first.pid} of user {getpass.getuser()} "
                             f"(matrix.yaml · pilotnet · onnxruntime none fp32, since "
                             f"{time.strftime('%H:%M:%S', time.localtime(a['window']['start']))})"]


def test_a_killed_holder_frees_the_slot_at_once_and_is_never_named(lock_dir):
    holder = start_holder("killed run", 60)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert json.loads((lock_dir / machine_lock.HOLDER_FILE).read_text())["pid"] == holder.pid  # left behind
    assert current_holder(lock_dir) is None
    assert str(holder.pid) not in waiting_message(lock_dir)
    messages: list[str] = []
    with timing_slot("next run", on_wait=messages.append) as window:
        pass
    assert messages == [] and window.waited_s == 0 and window.end is not None  # taken at the first try


def test_a_reused_pid_or_another_host_is_not_a_holder(lock_dir):
    with timing_slot("me"):
        named = current_holder(lock_dir)
        assert named is not None and named.pid == os.getpid() and named.holder == "me"
        info = json.loads((lock_dir / machine_lock.HOLDER_FILE).read_text())
    stale = ({"started": info["started"] + 1}, {"started": None}, {"host": info["host"] + "-elsewhere"})
    for changed in stale:
        (lock_dir / machine_lock.HOLDER_FILE).write_text(json.dumps({**info, **changed}))
        assert current_holder(lock_dir) is None
    (lock_dir / machine_lock.HOLDER_FILE).write_text("{not json")
    assert "held by an unnamed process" in waiting_message(lock_dir)


def test_the_sidecar_is_emptied_on_release(lock_dir):
    with timing_slot("me"):
        pass
    assert (lock_dir / machine_lock.HOLDER_FILE).read_text() == ""
    assert current_holder(lock_dir) is None


def test_the_wait_is_repeated_with_its_length_and_stops_once_held(monkeypatch):
    monkeypatch.setattr(machine_lock, "REMIND_EVERY_S", 0.2)
    holder = start_holder("slow run")
    release(holder, after_s=30)  # at the latest, should no reminder come
    messages: list[str] = []

    def heard(message: str) -> None:
        messages.append(message)
        if "; waited " in message:  # a reminder saying how long: let go
            release(holder)

    begin = time.monotonic()
    with timing_slot("me", on_wait=heard):
        count, waited = len(messages), time.monotonic() - begin
    time.sleep(3 * machine_lock.REMIND_EVERY_S)
    assert len(messages) == count >= 2  # the first message, then a reminder; none once held
    assert all(f"pid {holder.pid} " in message for message in messages)
    assert "; waited " not in messages[0]
    lengths = [int(m.group(1)) for m in map(re.compile(r"; waited (\d+) s$").search, messages[1:]) if m]
    assert lengths and lengths == sorted(lengths) and 1 <= lengths[-1] <= waited, messages
    finish(holder)


def test_files_are_shared_with_every_user_despite_a_narrow_umask(lock_dir):
    old = os.umask(0o077)
    try:
        with timing_slot("me"):
            pass
    finally:
        os.umask(old)
    assert stat.S_IMODE(lock_dir.stat().st_mode) == 0o1777
    assert stat.S_IMODE((lock_dir / machine_lock.LOCK_FILE).stat().st_mode) == 0o644
    assert stat.S_IMODE((lock_dir / machine_lock.HOLDER_FILE).stat().st_mode) == 0o666


def test_an_unusable_lock_directory_is_a_clear_error(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    monkeypatch.setenv(machine_lock.LOCK_DIR_VARIABLE, str(tmp_path / "file" / "lock"))
    with pytest.raises(UserError, match=r"cannot use the machine's timing lock in .*file/lock: .*"
                                        r"BENCH_MATRIX_LOCK_DIR"):
        with timing_slot("me"):
            pass


def release_once_waiting(holder: subprocess.Popen, events: list[str]) -> Callable[[str], None]:
    """An `on_phase` noting each phase in `events` and letting `holder` go 2 s after the child waits for it:
    a wait longer than the 1-s limits below, however slowly the child started."""
    def seen(event: str) -> None:
        events.append(event)
        if event.startswith("waiting for "):
            release(holder, after_s=2.0)
    return seen


def test_the_launcher_does_not_count_the_wait_against_the_time_limit(tmp_path):
    holder = start_holder("long run")
    events: list[str] = []
    ended = run_in_process(SlotJob(0.1), tmp_path / "jobs", tmp_path / "log.txt", timeout_s=1,
                           on_phase=release_once_waiting(holder, events),
                           tick=lambda: events.append("<tick>"))
    assert ended.ok, ended.error
    assert ended.result["waited_s"] >= 2.0
    phases = [e for e in events if e != "<tick>"]
    assert phases[0] == "load" and phases[-1] == "measure" and len(phases) == 3
    assert phases[1].startswith(f"waiting for the timing phase of pid {holder.pid} ")
    assert "(long run, since " in phases[1]
    waiting_ticks = events[events.index(phases[1]) + 1:events.index("measure")]
    assert waiting_ticks == []  # no timer while another run measures
    finish(holder)


def test_the_time_limit_still_applies_after_the_wait(tmp_path):
    holder = start_holder("long run")
    ended = run_in_process(SlotJob(60), tmp_path / "jobs", tmp_path / "log.txt", timeout_s=1,
                           on_phase=release_once_waiting(holder, []))
    assert not ended.ok  # killed after the wait (in 'measure'), which was longer than the limit
    found = re.search(r"timed out after 1 s \(in phase 'measure', not counting (\d+) s waiting for the "
                      r"timing lock\)", ended.error)
    assert found and int(found.group(1)) >= 2, ended.error
    finish(holder)
