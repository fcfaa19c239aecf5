"""Closed-loop driving through the CLI with real runtimes: the matrix section, the laps stored beside the
offline figures, the report's simulation table and trajectory plots, models that cannot drive, a trained
PilotNet in lock-step (completes, deterministic) and in real time against an artificially slowed copy."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import FAST_SETTINGS, cli, install_slow_plugin, matrix_text, onnx_matrix_text
from laps import slowest_rate

PILOTNET = """\
models: [{{name: pilotnet, framework: pytorch, builtin: pilotnet{training}}}]
dataset: {{builtin: driving, samples: {samples}, circuits: {circuits}, seed: 0}}
axes: {{backend: {backends}, strategy: [none], precision: [fp32], target: [cpu]}}
"""
# samples of the trained PilotNet, a quarter of the default: trained on dataset seeds 0 to 3 alike, it
# completed the lap (deviation MAE 0.14 to 0.41 m; on 800 samples it left the road with two of them), in
# half the training time of 2000 samples
TRAINED = 1000
SLOW_MS = 400  # the slowed brain's delay: late enough to drive worse with the model trained on TRAINED
# the real-time laps' simulated seconds, as many wall seconds for the slowed brain (the simulator never
# sleeps, its brain does): in 6 s it deviated about 3x as much as in lock-step and covered less of the
# lap (it left the road after about 10 s)
SLOW_LAP_S = 6
DRIVE_KEYS = ("stop_reason", "completed_pct", "lap_time_s", "sim_time_s", "distance_m", "avg_speed_mps",
              "deviation_mae_m", "deviation_max_m", "off_road_s", "road_departures", "brain_steps",
              "brain_hz", "suddenness", "driving_score", "trajectory")  # everything but wall-clock timings


def pilotnet_matrix(backends: str, closed_loop: str, samples: int = 4000, circuits: int = 20,
                    training: str = "", eval_samples: int = 64) -> str:
    return (PILOTNET.format(backends=backends, samples=samples, circuits=circuits, training=training)
            + FAST_SETTINGS.replace("}\n", f", eval_samples: {eval_samples}}}\n") + closed_loop)


def records(project: Path, env: dict[str, str] | None = None) -> dict[str, dict]:
    out = cli(project, "report", "--format", "json", env=env)
    assert out.returncode == 0, out.stderr
    return {r["cell"]["backend"]: r for r in json.loads(out.stdout)["records"]}


def run(project: Path, text: str, *args: str, env: dict[str, str] | None = None) -> None:
    (project / "m.yaml").write_text(text)
    out = cli(project, "run", "m.yaml", *args, env=env, timeout=900)
    assert out.returncode == 0, out.stdout + out.stderr


def driving(lap: dict) -> dict:
    return {key: lap[key] for key in DRIVE_KEYS}


@pytest.mark.slow
def test_cli_drives_a_small_pilotnet_on_the_oval_and_reports_it(tmp_path: Path) -> None:
    text = pilotnet_matrix("[onnxruntime]", "closed_loop: {circuits: [oval], time_limit_s: 10}\n", samples=200,
                           circuits=4, training=", training: {epochs: 1}")
    run(tmp_path, text)
    record = records(tmp_path)["onnxruntime"]
    assert record["status"] == "ok" and record["metrics"]["mse"] > 0  # the offline figures are there too
    assert record["metrics"]["rounds"]["rounds"] >= 2  # timed in rounds, the laps driven after them
    laps = record["metrics"]["closed_loop"]["oval"]
    assert set(laps) == {"lock_step", "real_time"}
    for lap in laps.values():
        assert lap["stop_reason"] in ("lap_completed", "off_road", "stuck", "time_limit")
        assert 0 <= lap["completed_pct"] <= 100 and lap["sim_time_s"] <= 10.0 + 1e-6
        assert lap["inference_ms"]["n"] == lap["brain_steps"] > 0 and lap["rtf"] > 0
        assert len(lap["trajectory"]["x"]) == len(lap["trajectory"]["y"]) >= 2
    assert record["metrics"]["closed_loop_circuits"]["oval"]["length_m"] == pytest.approx(277, abs=1)
    out = cli(tmp_path, "report", "--format", "md", "--out", str(tmp_path / "pages"))
    assert out.returncode == 0, out.stderr
    page = (tmp_path / "pages" / "pilotnet.md").read_text()
    plot = "trajectory-pilotnet__onnxruntime__none__fp32__cpu.png"
    assert "## Closed loop" in page and f"](plots/{plot})" in page
    assert "| onnxruntime none fp32 | oval | lock-step |" in page
    assert (tmp_path / "pages" / "plots" / plot).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_a_model_that_cannot_drive_is_skipped_by_all_and_refused_when_named(onnx_project: Path) -> None:
    section = "closed_loop: {circuits: [oval], modes: [lock_step]}\n"
    run(onnx_project, onnx_matrix_text(["tiny"], ["fp32"], section))
    record = records(onnx_project)["onnxruntime"]
    assert record["status"] == "ok" and "closed_loop" not in record["metrics"]
    assert "model tiny cannot drive" in record["metrics"]["closed_loop_skipped"]
    named = section.replace("}\n", ", cells: [{model: tiny}]}\n")
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"], named))
    out = cli(onnx_project, "plan", "m.yaml")
    assert out.returncode == 2
    assert "m.yaml:6: closed_loop.cells[0].model: model tiny cannot drive" in out.stderr


@pytest.mark.parametrize("section, message", [
    ("closed_loop: {modes: [lockstep]}",
     "closed_loop.modes[0]: 'lockstep' is not allowed; allowed: lock_step, real_time; did you mean "
     "'lock_step'?"),
    ("closed_loop: {circuits: [simpel]}", "closed_loop.circuits[0]: 'simpel' is not allowed; allowed: oval, "
                                          "simple, curvy, twisty, hairpin; did you mean "
                                          "'simple'?"),
    ("closed_loop: {vehicle: {steering_tau_ms: -1}}",
     "closed_loop.vehicle.steering_tau_ms: must be >= 0, got -1"),
    ("closed_loop: {margins: {latency: {}, circuits: [oval]}}",
     "closed_loop.margins.circuits[0]: 'oval' is not one of the section's circuits (simple)"),
    ("closed_loop: {margins: {circuits: [simple]}}",
     "closed_loop.margins: name at least one margin to search: latency, speed, perception"),
    ("closed_loop: {margins: {speed: {limit: 1.02}}}",
     "closed_loop.margins.speed: the speed margin's search from 1 to its limit 1.02 must span at least its "
     "resolution 0.05"),
    ("closed_loop: {margins: {perception: {kind: fog}}}",
     "closed_loop.margins.perception.kind: 'fog' is not allowed; allowed: light, noise, blur, mix"),
    ("closed_loop: {vehicle: small}",
     "closed_loop.vehicle: 'small' is not allowed; allowed: ideal, small_robot"),
    ("closed_loop: {brain_period_ms: 0}", "closed_loop.brain_period_ms: must be >= 1, got 0"),
    ("closed_loop: {cells: some}", "closed_loop.cells: 'some' is not allowed; allowed: all"),
    ("closed_loop: {circuits: [{name: mine, points: [[0, 0], [10, 0], [10, 6], [0, 6]]}]}",
     "closed_loop.circuits[0].points: circuit mine: the circuit is 35 m long; give at least 60 m"),
    ("closed_loop: {exclude: [{backend: onnxruntim}]}",
     "closed_loop.exclude[0].backend: 'onnxruntim' is not a known backend"),
])
def test_bad_closed_loop_section_exits_2_naming_file_key_and_allowed(tiny_project: Path, section: str,
                                                                      message: str) -> None:
    text = matrix_text(["onnxruntime"], ["none"], ["fp32"], ["cpu"], section + "\n")
    (tiny_project / "m.yaml").write_text(text)
    out = cli(tiny_project, "plan", "m.yaml")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert f"m.yaml:6: {message}" in out.stderr


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A project whose workspace holds a PilotNet trained on a quarter of the default driving data (1000
    samples of 10 circuits, 8 epochs) and its lock-step lap of the default circuit."""
    project = tmp_path_factory.mktemp("trained")
    run(project, pilotnet_matrix("[onnxruntime]", "closed_loop: {modes: [lock_step]}\n", TRAINED, 10))
    return project


@pytest.mark.slow
def test_trained_pilotnet_completes_the_default_circuit_deterministically(trained: Path) -> None:
    first = records(trained)["onnxruntime"]["metrics"]["closed_loop"]["simple"]["lock_step"]
    assert first["stop_reason"] == "lap_completed" and first["completed_pct"] == 100.0, first
    assert first["road_departures"] == 0 and first["deviation_mae_m"] < 1.5
    run(trained, (trained / "m.yaml").read_text(), "--force")  # the same cell and artifact, measured again
    second = records(trained)["onnxruntime"]["metrics"]["closed_loop"]["simple"]["lock_step"]
    assert driving(second) == driving(first)


@pytest.mark.slow
def test_a_slowed_brain_drives_worse_in_real_time(trained: Path) -> None:
    """The slowed brain's commands come at least SLOW_MS late however busy the machine; the reference is the
    same model in lock-step for as long (no time passes while it thinks: the same lap on any machine)."""
    env = {**install_slow_plugin(trained), "SLOW_ORT_DELAY_MS": str(SLOW_MS)}
    section = f"closed_loop: {{modes: [MODE], time_limit_s: {SLOW_LAP_S}}}\n"
    # one evaluation batch: each batch costs the slowed brain its delay
    run(trained, pilotnet_matrix("[onnxruntime]", section.replace("MODE", "lock_step"), TRAINED, 10,
                                 eval_samples=8), env=env)
    steady = records(trained, env)["onnxruntime"]["metrics"]["closed_loop"]["simple"]["lock_step"]
    run(trained, pilotnet_matrix("[onnxruntime, slow_ort]", section.replace("MODE", "real_time"), TRAINED, 10,
                                 eval_samples=8), env=env)
    found = records(trained, env)
    quick, slow = (found[backend]["metrics"]["closed_loop"]["simple"]["real_time"]
                   for backend in ("onnxruntime", "slow_ort"))
    assert slow["inference_ms"]["p50"] > SLOW_MS > 10 * quick["inference_ms"]["p50"]
    assert slowest_rate(slow) <= slow["brain_hz"] < 2.6  # 2.4-2.5 Hz: 41 physics steps a decision
    assert slowest_rate(quick) <= quick["brain_hz"]  # late by its own measured time, not more (~20 Hz)
    assert slow["completed_pct"] < steady["completed_pct"] and \
        slow["deviation_mae_m"] > 1.3 * steady["deviation_mae_m"], (steady, slow)


@pytest.mark.slow
def test_margins_of_a_trained_pilotnet_are_searched_with_its_own_session(trained: Path) -> None:
    """Each probe a lock-step lap of the cell's session on the lagged car: the record holds every search's
    answer and probes, the report its margins table and plot."""
    section = ("closed_loop: {circuits: [oval], modes: [lock_step], vehicle: small_robot, margins: "
               "{latency: {limit_ms: 200, resolution_ms: 100}, speed: {limit: 1.5, resolution: 0.5}, "
               "perception: {limit: 0.5, resolution: 0.5, kind: mix, seed: 3}}}\n")
    run(trained, pilotnet_matrix("[onnxruntime]", section, TRAINED, 10))
    record = records(trained)["onnxruntime"]
    margins = record["metrics"]["closed_loop_margins"]["oval"]
    assert list(margins) == ["latency", "speed", "perception"]
    for kind, answer in margins.items():
        assert answer["outcome"] in ("found", "passes_at_limit", "fails_at_start"), answer
        assert answer["laps"] == len(answer["probes"]) >= 1 and answer["wall_s"] > 0
        assert answer["probes"][0][0] == answer["start"] and answer["resolution"] == {
            "latency": 100, "speed": 0.5, "perception": 0.5}[kind]
        if answer["outcome"] == "found":
            assert [answer["value"], True] in answer["probes"]
            assert [answer["failed_at"], False] in answer["probes"]
    assert margins["perception"]["perturbation"] == "mix" and margins["perception"]["seed"] == 3
    out = cli(trained, "report", "--format", "md", "--out", str(trained / "pages"))
    assert out.returncode == 0, out.stderr
    page = (trained / "pages" / "pilotnet.md").read_text()
    assert "### Closed-loop margins" in page and "| onnxruntime none fp32 | oval |" in page
    assert (trained / "pages" / "plots" / "margins-pilotnet.png").read_bytes()[:4] == b"\x89PNG"
