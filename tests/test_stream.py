"""The stream scenario: its loop's accounting on an injected clock (skip and queue, misses, drops, jitter, the
precise wait), then through the CLI with real ONNX Runtime sessions, one slowed past the frame period (it
misses every deadline and drops frames), the figures stored and reported, a requirement on them failing the
verdict, and a bad section refused with its location."""

from __future__ import annotations

import gc
import json
import sqlite3
from pathlib import Path

import pytest

from bench_matrix.measure.stats import unpack_samples
from bench_matrix.scenarios.stream.run import SPIN_NS, figures, serve, wait_until
from conftest import cli, install_slow_plugin, onnx_matrix_text

MS = 1_000_000  # ns
PERIOD = 10 * MS
SLOW_MS = 30  # the slowed session's delay per call: past the 20 ms period of the end-to-end stream
STREAM = "stream: {rate_hz: 50, duration_s: 1, policy: skip}\nrequirements: {stream: {miss_share: 0.5}}\n"


class FakeClock:
    """A clock that waits exactly and whose calls take the given milliseconds, in turn."""

    def __init__(self, service_ms: list[float]):
        self.t, self.service = 0, iter(service_ms)

    def now(self) -> int:
        return self.t

    def wait_until(self, t_ns: int) -> None:
        self.t = max(self.t, t_ns)

    def call(self, _: object) -> None:
        self.t += round(next(self.service) * MS)


def streamed(service_ms: list[float], frames: int, policy: str) -> dict:
    clock = FakeClock(service_ms)
    return figures(serve(clock.call, [None], frames, PERIOD, policy, clock))


def test_skip_drops_the_frames_that_arrived_during_a_late_call() -> None:
    found = streamed([5, 25, 5, 5, 12], 8, "skip")  # frames 0, 1 (late: drops 2, 3), 4, 5, 6 (late: drops 7)
    assert found["completed"] == 5 and found["dropped"] == 3 and found["drop_share"] == 3 / 8
    assert found["missed"] == 2 and found["miss_share"] == 0.4
    assert found["achieved_hz"] == pytest.approx(5 / 0.080)  # completed ÷ the stream's 80 ms
    # completions at 5, 35, 45, 55, 72 ms: intervals 30, 10, 10, 17 against the 10 ms period
    assert found["jitter_p50_ms"] == pytest.approx(3.5) and found["jitter_p99_ms"] == pytest.approx(19.61)
    assert found["latency_p50_ms"] == 5 and found["e2e_p50_ms"] == 5  # each call starts at its frame


def test_queue_serves_every_frame_and_counts_the_wait_end_to_end() -> None:
    found = streamed([5, 25, 5, 5, 12, 5, 5, 5], 8, "queue")
    assert found["completed"] == 8 and found["dropped"] == 0 and found["missed"] == 5
    assert found["latency_p50_ms"] == 5  # service times 5, 25, 5, 5, 12, 5, 5, 5
    assert found["e2e_p50_ms"] == pytest.approx(13.5)  # arrival to end: 5, 25, 20, 15, 17, 12, 7, 5
    assert found["e2e_p99_ms"] == pytest.approx(24.65)


def test_a_call_slower_than_the_period_sets_the_rate() -> None:
    queued = streamed([15] * 4, 4, "queue")
    assert queued["achieved_hz"] == pytest.approx(4 / 0.060)  # the last call ends at 60 ms, after 40 ms
    assert queued["miss_share"] == 1.0 and queued["jitter_p50_ms"] == pytest.approx(5.0)
    skipped = streamed([15] * 2, 4, "skip")  # frames 0 and 2 served, 1 and 3 dropped
    assert (skipped["completed"], skipped["dropped"], skipped["missed"]) == (2, 2, 2)
    assert skipped["jitter_p50_ms"] == pytest.approx(10.0)  # completions 20 ms apart


def test_a_queue_fallen_behind_is_cut_at_twice_its_duration_the_rest_dropped() -> None:
    found = streamed([35] * 3, 4, "queue")  # 40 ms of frames: calls end at 35, 70, 105 ms; the cut is at 80
    assert (found["completed"], found["dropped"], found["missed"]) == (3, 1, 3)
    assert found["achieved_hz"] == pytest.approx(3 / 0.105)


def test_a_stream_keeping_up_has_no_miss_no_drop_no_jitter() -> None:
    found = streamed([2] * 5, 5, "skip")
    assert (found["missed"], found["dropped"], found["achieved_hz"]) == (0, 0, 100.0)
    assert found["jitter_p99_ms"] == 0 and found["e2e_p99_ms"] == pytest.approx(2.0)


def test_one_completed_call_has_no_jitter_stored_as_none() -> None:
    found = streamed([50], 2, "skip")
    assert found["completed"] == 1 and found["jitter_p50_ms"] is None and found["jitter_p99_ms"] is None


def test_the_stream_runs_without_the_garbage_collector() -> None:
    enabled: list[bool] = []
    clock = FakeClock([1, 1])
    serve(lambda x: (enabled.append(gc.isenabled()), clock.call(x)), [None], 2, PERIOD, "skip", clock)
    assert enabled == [False, False] and gc.isenabled()


def test_the_wait_sleeps_most_of_the_way_then_spins() -> None:
    t, sleeps = [0], []

    def now() -> int:
        t[0] += 100_000  # every reading of the clock takes 0.1 ms
        return t[0]

    def sleep(seconds: float) -> None:
        sleeps.append(seconds)
        t[0] += round(seconds * 1e9)

    wait_until(10 * MS, now, sleep)
    assert sleeps == [pytest.approx((10 * MS - 100_000 - SPIN_NS) / 1e9)]  # one sleep, then spinning
    assert 10 * MS <= t[0] < 10 * MS + 100_000
    wait_until(5 * MS, now, sleep)  # passed already: no sleep
    assert len(sleeps) == 1


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """tiny.onnx through ONNX Runtime and through ONNX Runtime slowed by SLOW_MS a call, streamed at 50 Hz."""
    import fuzz_cases

    project = fuzz_cases.write_project(tmp_path_factory.mktemp("stream"))
    env = {**install_slow_plugin(project), "SLOW_ORT_DELAY_MS": str(SLOW_MS)}
    text = onnx_matrix_text(["tiny"], ["fp32"], STREAM).replace("[onnxruntime]", "[onnxruntime, slow_ort]")
    (project / "m.yaml").write_text(text)
    out = cli(project, "run", "m.yaml", env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    return project, env


def _records(project: Path, env: dict[str, str]) -> dict[str, dict]:
    out = cli(project, "report", "--format", "json", env=env)
    assert out.returncode == 0, out.stderr
    return {r["cell"]["backend"]: r for r in json.loads(out.stdout)["records"]}


@pytest.mark.slow
def test_a_session_slower_than_the_period_misses_deadlines(measured: tuple[Path, dict[str, str]]) -> None:
    record = _records(*measured)["slow_ort"]
    slow = record["metrics"]["stream"]
    assert (slow["rate_hz"], slow["duration_s"], slow["policy"], slow["frames"]) == (50, 1, "skip", 50)
    assert slow["missed"] == slow["completed"] > 0 and slow["miss_share"] == 1.0
    assert slow["completed"] + slow["dropped"] == 50 and slow["dropped"] >= slow["completed"] - 1
    assert slow["latency_p50_ms"] >= SLOW_MS and slow["achieved_hz"] <= 50 / 2
    assert all(value is not None for value in slow.values())
    store = sqlite3.connect(measured[0] / "ws" / "results.sqlite")
    series = dict(store.execute("SELECT series, data FROM samples WHERE record_id = ? AND series LIKE "
                                "'stream_%'", (record["record"],)))
    service, e2e = unpack_samples(series["stream_latency_ms"]), unpack_samples(series["stream_e2e_ms"])
    assert len(service) == len(e2e) == slow["completed"] and service.min() >= SLOW_MS


@pytest.mark.slow
def test_a_fast_session_keeps_up_and_its_figures_are_reported(measured: tuple[Path, dict[str, str]]) -> None:
    project, env = measured
    fast = _records(project, env)["onnxruntime"]["metrics"]["stream"]
    assert fast["completed"] + fast["dropped"] == fast["frames"] == 50
    assert fast["miss_share"] <= 0.5 and fast["latency_p50_ms"] < 20  # structural on a busy machine
    out = cli(project, "report", "--format", "md", "--out", str(project / "pages"), env=env)
    assert out.returncode == 0, out.stderr
    page = (project / "pages" / "tiny.md").read_text()
    assert "## Stream" in page and "| slow_ort none fp32 | skip | 50 |" in page
    out = cli(project, "report", "--format", "html", "--out", str(project / "html"), env=env)
    assert out.returncode == 0 and "<h3>Stream</h3>" in (project / "html" / "report.html").read_text()


@pytest.mark.slow
def test_a_requirement_on_a_stream_figure_fails_the_verdict(measured: tuple[Path, dict[str, str]]) -> None:
    project, env = measured
    verdict = _records(project, env)["slow_ort"]["verdict"]
    assert verdict["status"] == "fail" and "stream.miss_share 1 > 0.5" in verdict["failed"][0]["text"]
    out = cli(project, "report", "--check", "--require", "stream.achieved_hz=1000", env=env)
    assert out.returncode == 1 and "stream.achieved_hz" in out.stdout


@pytest.mark.slow
def test_a_bad_stream_value_exits_2_naming_file_key_and_allowed_values(onnx_project: Path) -> None:
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"], "stream: {policy: latest}\n"))
    out = cli(onnx_project, "plan", "m.yaml")
    assert out.returncode == 2
    assert "m.yaml:6: stream.policy: 'latest' is not allowed; allowed: skip, queue" in out.stderr
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"], "stream: {duration_s: 0.01}\n"))
    out = cli(onnx_project, "plan", "m.yaml")
    assert out.returncode == 2
    assert "m.yaml:6: stream.duration_s: rate_hz × duration_s makes 0 frames" in out.stderr


def test_a_cell_that_streams_finishes_holding_the_machine_timing_lock(tmp_path: Path) -> None:
    from contextlib import contextmanager
    from types import SimpleNamespace

    from bench_matrix.executors.rounds import _Sessions
    from bench_matrix.scenarios.stream import StreamPlan
    from bench_matrix.scenarios.stream.spec import StreamSpec

    held: list[str] = []
    finishing: list[str] = []

    @contextmanager
    def hold():
        held.append("enter")
        yield
        held.append("exit")

    def cell(key: str, scenarios: tuple) -> SimpleNamespace:
        return SimpleNamespace(id=key, cell=SimpleNamespace(label=key), scenarios=scenarios,
                               settings=SimpleNamespace(processes=2))

    job = SimpleNamespace(cells=(cell("plain", ()), cell("streams", (StreamPlan(StreamSpec()),))),
                          logs=("a.log", "b.log"))
    sessions = _Sessions(job, tmp_path, tmp_path, lambda _: None, hold=hold)
    closed: list[str] = []
    first = SimpleNamespace(finish=lambda: finishing.append(list(held)), close=lambda: closed.append("first"))
    second = SimpleNamespace(finish=lambda: finishing.append(["second"]),
                             close=lambda: closed.append("second"))
    sessions.close("plain", [first, second])
    sessions.close("streams", [first, second])
    assert finishing == [[], ["enter"]] and held == ["enter", "exit"]  # finished in its first process only
    assert closed == ["first", "second"] * 2
