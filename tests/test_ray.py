"""`run --executor ray` on a simulated two-node Ray cluster on this machine: each node with its own workspace
(so the shared preparation really travels through the object store), its own host name and its own timing
lock; one cluster for the module (Ray takes seconds to start)."""

from __future__ import annotations

import io
import json
import os
import signal
import sqlite3
import subprocess
import sys
import tarfile
from importlib.util import find_spec
from pathlib import Path

import pytest
from conftest import cli, onnx_matrix_text, popen_cli
from lock_helpers import flock_waiters, release, start_holder
from polling import wait_for

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.jobs import ConvertJob, MeasureJob, PreparedData
from bench_matrix.jobs.results import Converted
from bench_matrix.matrix.spec import Settings
from bench_matrix.measure.machine_lock import LOCK_FILE, current_holder
from bench_matrix.sources import SourceModel
from bench_matrix.workspace import Workspace

needs_ray = pytest.mark.skipif(find_spec("ray") is None,
                               reason="Ray is not installed (pip install 'bench-matrix[ray]')")
NODES = ("node-a", "node-b")
# two ONNX models at two precisions on the CPU, plus their CUDA cells (skipped: no node has a GPU)
MATRIX = onnx_matrix_text(["tiny", "twin"], ["fp32", "fp16"]).replace("target: [cpu]", "target: [cpu, cuda]")
# rounds long enough to be seen, and their task killed, as they run: the budget's 3 s, not 2 rounds whose
# medians happened to agree to the nanosecond (0 width: seen in CI, which left no time for the next kill)
SLOW = (("min_rounds: 2", "min_rounds: 50"),
        ("timing_budget_s: 0.05", "timing_budget_s: 3, ci_target: 0.0001"))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory):
    """A head without CPUs and two one-CPU nodes offering the timing resource; (cluster, nodes' root)."""
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage statistics sent from our test clusters
    root = tmp_path_factory.mktemp("nodes")
    memory = 100 * 2**20
    simulated = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False,
                                                              "object_store_memory": memory})
    for name in NODES:
        own = {"BENCH_MATRIX_HOST": name, "BENCH_MATRIX_NODE_WORKSPACE": str(root / name),
               "BENCH_MATRIX_LOCK_DIR": str(root / f"{name}-lock")}
        simulated.add_node(num_cpus=1, resources={"bench_matrix_timing": 1}, object_store_memory=memory,
                           env_vars=own)
    yield simulated, root
    simulated.shutdown()


def _records(db: Path) -> list[dict]:
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT key, status, host, reason, env, metrics, artifact_path FROM records "
                           "ORDER BY id").fetchall()
    return [{"key": k, "status": s, "host": h, "reason": r, "env": json.loads(e), "metrics": json.loads(m),
             "artifact": a} for k, s, h, r, e, m, a in rows]


def _cells(records: list[dict]) -> list[tuple[str, str]]:
    return sorted((r["key"], r["status"]) for r in records)


def _records_so_far(db: Path) -> list[dict]:
    """The records a run has written so far (none before it has created its tables)."""
    try:
        return _records(db) if db.is_file() else []
    except sqlite3.OperationalError:
        return []


def _ok(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_without_ray_the_executor_says_what_to_install(onnx_project):
    (onnx_project / "m.yaml").write_text(MATRIX)
    code = ("import sys; sys.modules['ray'] = None; from bench_matrix.cli import main; "
            "sys.exit(main(['--workspace', 'ws', 'run', 'm.yaml', '--executor', 'ray']))")
    out = subprocess.run([sys.executable, "-c", code], cwd=onnx_project, capture_output=True, text=True)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "--executor ray needs Ray" in out.stderr and "pip install 'bench-matrix[ray]'" in out.stderr
    local = cli(onnx_project, "run", "m.yaml", "--address", "somewhere:6379")
    assert local.returncode == 2 and "use it with --executor ray" in local.stderr


def test_jobs_move_to_a_node_workspace_with_the_shipped_paths(tmp_path):
    from bench_matrix.executors.ray_tasks import relocate

    ws, node = Workspace(tmp_path / "driver"), Workspace(tmp_path / "node")
    data = PreparedData(ws.datasets("d1"), {"fingerprint": "d1"}, None)
    source = SourceModel("m", "onnx", "onnx", tmp_path / "project" / "m.onnx", "0" * 64, ())
    cell = Cell("m", "onnx", "onnxruntime", "none", "fp32", "cpu")
    convert = ConvertJob(ws, cell, CellPlan(cell, "run").step, source, data, "nhwc", Settings(), {})
    converted = Converted(node.artifact("onnxruntime", "a1"), {}, False)  # made on the node: it stays
    measure = MeasureJob(ws, cell, "regression", converted, source, data, "nhwc", Settings(),
                         ws.models("k") / "reference.npz")
    moved = {str(data.directory): "/n/d1", str(source.path): "/n/src/m.onnx", str(ws.models("k")): "/n/k"}
    convert, measure = relocate((convert, measure), moved, node)
    assert convert.workspace == node and measure.workspace == node
    assert convert.data.directory == Path("/n/d1") and measure.data.info == {"fingerprint": "d1"}
    assert convert.source.path == Path("/n/src/m.onnx")
    assert measure.reference == Path("/n/k/reference.npz") and measure.converted == converted
    assert measure.cell == cell and convert.settings == Settings()


def test_tasks_ask_for_a_gpu_where_the_backend_runs_the_target_on_cuda(tmp_path):
    """The GPU share follows each backend's `devices`, as the nodes' probes report them."""
    from bench_matrix.executors.ray_cluster import GPU_SHARE, gpu_share
    from bench_matrix.jobs import ProbeJob
    from bench_matrix.jobs.probe import probe

    known = probe(ProbeJob(Workspace(tmp_path), ("onnxruntime", "openvino"), keys=())).devices()

    def share(backend: str, target: str) -> float:
        return gpu_share(known, Cell("m", "onnx", backend, "none", "fp32", target))

    assert share("onnxruntime", "cuda") == share("onnxruntime", "tensorrt") == GPU_SHARE
    assert share("onnxruntime", "cpu") == share("openvino", "intel_gpu") == share("gone", "cuda") == 0


@needs_ray
@pytest.mark.slow
def test_a_ray_run_records_what_a_local_run_does_on_the_nodes(onnx_project, cluster):
    simulated, root = cluster
    (onnx_project / "m.yaml").write_text(MATRIX)
    _ok(cli(onnx_project, "run", "m.yaml", "--results", "local.sqlite"))
    _ok(cli(onnx_project, "run", "m.yaml", "--results", "ray.sqlite", "--executor", "ray",
            "--address", simulated.address))
    local, distributed = _records(onnx_project / "local.sqlite"), _records(onnx_project / "ray.sqlite")
    assert _cells(distributed) == _cells(local)
    measured = [r for r in distributed if r["status"] == "ok"]
    assert len(measured) == 4 and {r["host"] for r in measured} <= set(NODES)
    for r in measured:  # converted and measured in the node's own workspace, from what was shipped there
        assert r["artifact"].startswith(str(root / r["host"])) and r["env"]["ray"]["attempt"] == 1
        assert any((root / r["host"] / "shipped").iterdir())
    for kind in ("datasets", "models"):  # the dataset and the models were prepared on the nodes too
        assert any((root / host / "cache" / kind).is_dir() for host in NODES), kind
    skipped = [r for r in distributed if r["status"] == "skipped"]
    assert skipped and all("node-a, node-b: " in r["reason"] for r in skipped)  # each node's reason
    for host in NODES:  # one model's rounds at a time per node
        windows = sorted({tuple(span) for r in measured if r["host"] == host
                          for span in r["metrics"]["timing_window"]["held"]})
        assert all(end <= start for (_, end), (start, _) in zip(windows, windows[1:]))

    again = _ok(cli(onnx_project, "run", "m.yaml", "--results", "ray.sqlite", "--executor", "ray",
                    "--address", simulated.address))
    assert "0 ok" in again and "4 already stored" in again  # the nodes' records count as done


def _ray_task_above(pid: int) -> int | None:
    """The Ray worker process (titled `ray::TASK`) that `pid` is or runs under, if any."""
    while pid > 1:
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0]
            parent = int(Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            return None
        if title.startswith(b"ray::"):
            return pid
        pid = parent
    return None


def _timing_task(root: Path, done: set[int]) -> int | None:
    """The Ray worker (not in `done`) whose cell is timing: its measuring child holds a node's timing slot."""
    for name in NODES:
        holder = current_holder(root / f"{name}-lock")
        task = _ray_task_above(holder.pid) if holder else None
        if task and task not in done:
            return task
    return None


def _kill_measuring(count: int, proc: subprocess.Popen, root: Path) -> int:
    """SIGKILL the Ray worker of a cell while the cell is timing, `count` times (or until the run ends); how
    many."""
    killed: set[int] = set()
    while len(killed) < count:
        task = wait_for(lambda: -1 if proc.poll() is not None else _timing_task(root, killed),
                        "a cell timing on a node")
        if task < 0:
            break
        os.kill(task, signal.SIGKILL)
        killed.add(task)
    return len(killed)


@needs_ray
@pytest.mark.slow
def test_a_killed_task_process_is_retried_and_a_cell_lost_every_time_fails(onnx_project, cluster):
    simulated, root = cluster
    matrix = onnx_matrix_text(["tiny"], ["fp32"])
    for old, new in SLOW:
        matrix = matrix.replace(old, new)
    (onnx_project / "m.yaml").write_text(matrix)
    args = ("run", "m.yaml", "--executor", "ray", "--address", simulated.address, "--force")
    proc = popen_cli(onnx_project, *args)
    assert _kill_measuring(1, proc, root) == 1
    assert proc.wait(timeout=120) == 0, proc.stdout.read()
    [retried] = _records(onnx_project / "ws" / "results.sqlite")
    assert retried["status"] == "ok" and retried["env"]["ray"]["attempt"] == 2

    proc = popen_cli(onnx_project, *args)
    assert _kill_measuring(3, proc, root) == 3
    assert proc.wait(timeout=120) == 0, proc.stdout.read()
    lost = _records(onnx_project / "ws" / "results.sqlite")[-1]
    assert lost["status"] == "failed" and "lost on the Ray cluster (3 attempts)" in lost["reason"]
    assert "WorkerCrashedError" in lost["reason"] and lost["host"] in NODES


@needs_ray
@pytest.mark.slow
def test_ctrl_c_on_the_driver_keeps_finished_cells_and_the_run_resumes(onnx_project, cluster):
    simulated, root = cluster
    (onnx_project / "m.yaml").write_text(MATRIX)
    args = ("run", "m.yaml", "--executor", "ray", "--address", simulated.address)
    db = onnx_project / "ws" / "results.sqlite"
    lock = root / f"{NODES[1]}-lock"
    # the second node's slot held: a cell there waits for it, so the run cannot end before it is interrupted
    held = start_holder("the test", env={"BENCH_MATRIX_LOCK_DIR": str(lock)})
    proc = popen_cli(onnx_project, *args)

    def interruptible() -> bool:
        assert proc.poll() is None, proc.stdout.read()
        return flock_waiters(lock / LOCK_FILE) == 1 and any(r["status"] == "ok" for r in _records_so_far(db))

    wait_for(interruptible, "a cell stored and another waiting on the second node", timeout_s=180)
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=60)
    # the driver gone, Ray ends its tasks: nothing waits on the second node's slot any more
    wait_for(lambda: flock_waiters(lock / LOCK_FILE) == 0, "the waiting task ended with its driver",
             timeout_s=60)
    release(held)
    held.wait(timeout=60)
    assert proc.returncode == 130 and "interrupted" in output and "Traceback" not in output, output
    with sqlite3.connect(db) as con:
        [summary] = [json.loads(s) for (s,) in con.execute("SELECT summary FROM runs")]
    kept = [r["key"] for r in _records(db) if r["status"] == "ok"]
    assert summary["completed"] is False and 1 <= len(kept) < 4
    rerun = _ok(cli(onnx_project, *args))
    assert f"{4 - len(kept)} ok" in rerun and f"{len(kept)} already stored" in rerun


def test_an_onnx_model_travels_with_its_external_data(tmp_path):
    import numpy as np
    import onnx
    from onnx import helper, numpy_helper

    from bench_matrix.executors.ray_tasks import pack
    from bench_matrix.sources.onnx_file import external_data_files

    weight = numpy_helper.from_array(np.ones((4, 4), np.float32), "w")
    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 4])],
                              [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 4])], [weight])
    (tmp_path / "m").mkdir()
    onnx.save_model(helper.make_model(graph), tmp_path / "m" / "model.onnx", save_as_external_data=True,
                    all_tensors_to_one_file=True, location="weights.bin", size_threshold=0)
    model = tmp_path / "m" / "model.onnx"
    beside = external_data_files(model)
    assert beside == [tmp_path / "m" / "weights.bin"]
    key, data = pack(model, beside)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert sorted(tar.getnames()) == ["model.onnx", "weights.bin"]
    (tmp_path / "m" / "weights.bin").write_bytes(b"\0" * 80)  # new weights: new content key
    assert pack(model, beside)[0] != key
