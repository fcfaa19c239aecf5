"""`run --executor ssh` and `device check` against a real OpenSSH server on 127.0.0.1 (tests/ssh_server.py):
the device is this machine with a workspace, host name, timing lock and Python of its own; conversions run
here, measurements there."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
from pathlib import Path

import pytest
from conftest import TWO_PROCESSES, cli, install_slow_plugin, onnx_matrix_text, popen_cli
from polling import wait_for
from ssh_server import (Server, device_at, device_python, free_port, jetson_path, processes, start_server,
                        why_no_sshd)

NO_SSHD = why_no_sshd()
pytestmark = [pytest.mark.skipif(NO_SSHD is not None, reason=NO_SSHD or ""), pytest.mark.slow]
# two models of one slow_ort cell each: the first passes the device's gate, the second waits there
GATED = onnx_matrix_text(["tiny", "twin"], ["fp32"]).replace("[onnxruntime]", "[slow_ort]").replace(
    *TWO_PROCESSES)  # a cell's 2 processes pass the gate together


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Server:
    try:
        started = start_server(tmp_path_factory.mktemp("sshd"))
    except RuntimeError as exc:
        pytest.skip(f"sshd cannot start here: {exc}")
    yield started
    started.kill()


def _ssh(server: Server, python: Path, device_ws: Path, device: str | None = None) -> list[str]:
    """The options of a run (or, without the first two, a check) measuring on the test's device."""
    return ["--executor", "ssh", "--device", f"{device or server.device}={python}", "--ssh-config",
            str(server.config), "--device-workspace", str(device_ws)]


def _records(db: Path) -> list[dict]:
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT key, status, host, reason, env FROM records ORDER BY id").fetchall()
    return [{"key": k, "status": s, "host": h, "reason": r, "env": json.loads(e)} for k, s, h, r, e in rows]


def _ok(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def _remote_processes(device_ws: Path) -> list[str]:
    """Command lines of the processes working in the device's workspace."""
    return [command for _, _, command in processes().values() if str(device_ws) in command]


def _gated(project: Path, server: Server) -> tuple[list[str], dict[str, str], Path]:
    """GATED written, a device whose sessions after its first wait at a gate; the run's options, its env and
    the gate."""
    (project / "m.yaml").write_text(GATED)
    env = {**install_slow_plugin(project), "SLOW_ORT_DELAY_MS": "0"}
    gate = project / "gate"
    gate.mkdir()
    python = device_python(project / "device-python", "gated", project / "device-lock",
                           {**env, "SLOW_ORT_GATE": str(gate)})
    return _ssh(server, python, project / "device"), env, gate


def test_cells_are_measured_on_the_device_and_shipped_once(onnx_project, server):
    stream = "stream: {rate_hz: 100, duration_s: 0.2, policy: skip}\n"  # the stream runs on the device too
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32", "fp16"], stream))
    python = device_python(onnx_project / "device-python", "device-a", onnx_project / "device-lock",
                           jetson_path(onnx_project / "jetson"))
    device_ws = onnx_project / "device"
    _ok(cli(onnx_project, "run", "m.yaml", *_ssh(server, python, device_ws)))
    first = _records(onnx_project / "ws" / "results.sqlite")
    assert [(r["status"], r["host"]) for r in first] == [("ok", "device-a")] * 2
    assert {r["env"]["jetson"]["nvpmodel"] for r in first} == {"NV Power Mode: MAXN 0"}
    with sqlite3.connect(onnx_project / "ws" / "results.sqlite") as con:
        streams = [json.loads(m)["stream"] for (m,) in con.execute("SELECT metrics FROM records")]
    assert [(s["frames"], s["completed"] + s["dropped"]) for s in streams] == [(20, 20)] * 2
    facts = first[0]["env"]["ssh"]
    assert facts["device"] == server.device and facts["shipped_files"] > 0 and facts["attempt"] == 1
    shipped = sorted((device_ws / "shipped").iterdir())
    assert shipped and not list((onnx_project / "ws").glob("shipped"))  # the device holds them, not this one
    names = {p.name for p in (device_ws / "shipped").rglob("*.npy")}
    assert "test__y.npy" in names and not {n for n in names if n.startswith(("train__", "calibration__"))}

    _ok(cli(onnx_project, "run", "m.yaml", "--results", "second.sqlite", *_ssh(server, python, device_ws)))
    second = _records(onnx_project / "second.sqlite")
    assert [r["status"] for r in second] == ["ok", "ok"]
    assert {(r["env"]["ssh"]["shipped_bytes"], r["env"]["ssh"]["reused_files"]) for r in second} == {
        (0, facts["shipped_files"])}  # nothing shipped again
    assert sorted((device_ws / "shipped").iterdir()) == shipped


def test_a_device_without_a_backend_skips_its_cells_naming_the_device(onnx_project, server):
    """slow_ort is installed here, not on the device: its cell is skipped, the other measured there."""
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]).replace(
        "[onnxruntime]", "[onnxruntime, slow_ort]"))
    env = {**install_slow_plugin(onnx_project), "SLOW_ORT_DELAY_MS": "0"}
    python = device_python(onnx_project / "device-python", "device-b", onnx_project / "device-lock")
    out = _ok(cli(onnx_project, "run", "m.yaml", *_ssh(server, python, onnx_project / "device"), env=env))
    assert "1 ok, 1 skipped" in out
    by_backend = {r["key"].split("/")[1]: r for r in _records(onnx_project / "ws" / "results.sqlite")}
    assert by_backend["onnxruntime"]["status"] == "ok" and by_backend["onnxruntime"]["host"] == "device-b"
    skipped = by_backend["slow_ort"]
    assert skipped["status"] == "skipped" and skipped["reason"].startswith(f"{server.device}: ")
    assert "slow_ort" in skipped["reason"] and skipped["host"] == "device-b"  # the device judged it
    store = str(onnx_project / "ws" / "results.sqlite")
    _ok(cli(onnx_project, "compare", store, store, env=env))  # one host per side: comparable


def test_device_check_says_what_the_device_runs_and_what_it_lacks(onnx_project, server):
    python = device_python(onnx_project / "device-python", "device-c", onnx_project / "device-lock",
                           jetson_path(onnx_project / "jetson"))
    check = _ssh(server, python, onnx_project / "device")[2:]
    out = _ok(cli(onnx_project, "device", "check", *check[1:]))
    assert "host device-c" in out and "bench-matrix 0.1.0 (the same as here" in out
    assert "power mode   NV Power Mode: MAXN 0" in out and "clocks" in out
    assert "onnxruntime: cpu: ready" in out and "cpu " in out
    assert f"usable: `bench-matrix run MATRIX --executor ssh --device {server.device}={python}`" in out

    bare = cli(onnx_project, "device", "check", f"{server.device}=/usr/bin/python3", *check[2:])
    assert bare.returncode == 1 and "bench-matrix is not installed" in bare.stderr
    user_host, port = server.device.rsplit(":", 1)
    assert f"ssh -p {port} {user_host} /usr/bin/python3 -m pip install 'bench-matrix==0.1.0'" in bare.stderr
    missing = cli(onnx_project, "device", "check", f"{server.device}=/no/python", *check[2:])
    assert missing.returncode == 1 and "'/no/python' was not found" in missing.stderr


def test_a_device_whose_workspace_cannot_be_written_fails_its_cells_and_the_run(onnx_project, server):
    """The device's workspace under a file: no user, root included, can create it."""
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]))
    python = device_python(onnx_project / "device-python", "device-e", onnx_project / "device-lock")
    (onnx_project / "file").write_text("")
    options = _ssh(server, python, onnx_project / "file" / "device")
    check = cli(onnx_project, "device", "check", *options[3:])
    assert check.returncode == 1 and "probing the backends there failed" in check.stdout
    out = cli(onnx_project, "run", "m.yaml", *options)
    assert out.returncode == 1 and "1 failed" in out.stdout and "0 skipped" in out.stdout, out.stdout
    assert f"device {server.device} cannot measure: probing it failed" in out.stdout
    [record] = _records(onnx_project / "ws" / "results.sqlite")
    assert record["status"] == "failed" and "probing it failed" in record["reason"]
    assert record["host"] == "device-e"


def test_each_models_rounds_show_under_its_own_name(onnx_project, server):
    """The first model's rounds run on the device while this machine prepares the second."""
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny", "twin"], ["fp32"]))
    python = device_python(onnx_project / "device-python", "device-f", onnx_project / "device-lock")
    out = _ok(cli(onnx_project, "run", "m.yaml", *_ssh(server, python, onnx_project / "device")))
    rounds = [line.split("] ", 1)[1] for line in out.splitlines() if line.endswith(": round 1")]
    assert sorted(rounds) == [f"{model} · measuring 1 cells in rounds · {server.device}: round 1"
                              for model in ("tiny", "twin")]


def test_an_unreachable_device_fails_its_cells_and_a_refused_login_stops_first(onnx_project, server,
                                                                               tmp_path):
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]))
    python = device_python(onnx_project / "device-python", "device-d", onnx_project / "device-lock")
    closed = device_at(free_port())  # nothing listens there
    options = _ssh(server, python, onnx_project / "device", device=closed)
    out = cli(onnx_project, "run", "m.yaml", *options)
    [record] = _records(onnx_project / "ws" / "results.sqlite")
    assert out.returncode == 1 and "1 failed" in out.stdout and record["status"] == "failed"
    assert f"device {closed} is unreachable" in record["reason"] and "refused" in record["reason"]
    assert f"device {closed} is unreachable" in out.stdout
    check = cli(onnx_project, "device", "check", *options[3:])
    assert check.returncode == 2 and "is unreachable" in check.stderr

    stranger = tmp_path / "stranger_config"  # a key the server does not know
    stranger.write_text(server.config.read_text().replace("client_key", "host_key"))
    refused = cli(onnx_project, "run", "m.yaml", "--results", "refused.sqlite",
                  *_ssh(server, python, onnx_project / "device")[:4], "--ssh-config", str(stranger))
    assert refused.returncode == 2 and "ssh cannot log in (" in refused.stderr
    assert "Traceback" not in refused.stderr
    assert not (onnx_project / "refused.sqlite").exists() or not _records(onnx_project / "refused.sqlite")


def test_a_killed_sshd_fails_the_cells_with_the_reason_and_the_run_finishes(onnx_project, tmp_path):
    own = start_server(tmp_path / "sshd")
    options, env, gate = _gated(onnx_project, own)
    proc = popen_cli(onnx_project, "run", "m.yaml", *options, env=env)
    wait_for(lambda: list(gate.glob("waiting-*")), "the second model's session waiting at the device's gate")
    own.kill()
    output, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, output
    status = {r["key"].split("/")[0]: r for r in _records(onnx_project / "ws" / "results.sqlite")}
    assert status["tiny"]["status"] == "ok" and status["twin"]["status"] == "failed"
    assert f"the connection to device {own.device} dropped (2 attempts)" in status["twin"]["reason"]
    wait_for(lambda: not _remote_processes(onnx_project / "device"), "the device's processes ending")


def test_a_dropped_connection_retries_the_cell_once(onnx_project, server):
    options, env, gate = _gated(onnx_project, server)
    proc = popen_cli(onnx_project, "run", "m.yaml", *options, env=env)
    processes = 2  # a cell's, by default
    wait_for(lambda: len(list(gate.glob("waiting-*"))) == processes, "the second model's sessions waiting")
    server.drop_connections()
    wait_for(lambda: len(list(gate.glob("waiting-*"))) == 2 * processes, "the retried sessions at the gate")
    (gate / "open").touch()
    output, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, output
    attempts = {r["key"].split("/")[0]: r["env"]["ssh"]["attempt"]
                for r in _records(onnx_project / "ws" / "results.sqlite")}
    assert attempts == {"tiny": 1, "twin": 2}


def test_ctrl_c_stops_the_device_and_the_rerun_resumes(onnx_project, server):
    options, env, gate = _gated(onnx_project, server)
    proc = popen_cli(onnx_project, "run", "m.yaml", *options, env=env)
    wait_for(lambda: list(gate.glob("waiting-*")), "the second model's session waiting at the device's gate")
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in output and "Traceback" not in output
    wait_for(lambda: not _remote_processes(onnx_project / "device"), "the device's processes ending",
             timeout_s=10)
    with sqlite3.connect(onnx_project / "ws" / "results.sqlite") as con:
        [(summary,)] = con.execute("SELECT summary FROM runs").fetchall()
    assert json.loads(summary)["completed"] is False

    (gate / "open").touch()
    rerun = _ok(cli(onnx_project, "run", "m.yaml", *options, env=env))
    assert "1 ok" in rerun and "1 already stored" in rerun
