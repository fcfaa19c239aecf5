"""Ray executor throughput: cells/hour of one matrix run locally and on a simulated two-node Ray cluster on
this machine, what Ray adds per cell (scheduling, shipping, returning results) and what it costs once per run
(connecting, probing every node), and from those an estimate for 1,000 cells on 10 and 100 nodes.

The matrix: `--models` copies of the tests' tiny ONNX model (tests/fuzz_cases.py) x fp32, fp16 through ONNX
Runtime on the CPU (20 cells by default), with short timing windows. Each simulated node has 1 CPU, its own
workspace (so shared preparation goes through the object store) and host name, as real nodes would; both
share this machine's timing lock, so no two timing phases overlap (as on one real machine): what the
cluster gains is conversions (and Ray's scheduling) overlapping another cell's measurement.

    .venv/bin/python benchmarks/ray_throughput.py [--models 10] [--workdir DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
import fuzz_cases  # noqa: E402  (the tiny ONNX model and dataset the test suite runs)
from conftest import onnx_matrix_text  # noqa: E402

NODES = ("node-a", "node-b")


def run_cli(project: Path, results: str, *extra: str) -> float:
    """Run the matrix through the CLI into `results`; the run's wall time as the store records it."""
    subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), "run",
                    "m.yaml", "--results", results, "--force", *extra], check=True, capture_output=True,
                   cwd=project)
    with sqlite3.connect(project / results) as db:
        (summary,) = db.execute("SELECT summary FROM runs ORDER BY id DESC").fetchone()
    return json.loads(summary)["wall_s"]


def ray_facts(project: Path, results: str) -> list[dict]:
    """What each ok record of the latest run says about its placement (`env.ray`)."""
    with sqlite3.connect(project / results) as db:
        rows = db.execute("SELECT env FROM records WHERE status = 'ok' AND run_id = "
                          "(SELECT max(id) FROM runs)").fetchall()
    return [json.loads(env)["ray"] for (env,) in rows]


def start_cluster(root: Path):
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage statistics sent from this cluster
    memory = 100 * 2**20
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False,
                                                           "object_store_memory": memory})
    for name in NODES:
        # one timing lock for both: they are one machine, so their timing phases must not overlap either
        own = {"BENCH_MATRIX_HOST": name, "BENCH_MATRIX_NODE_WORKSPACE": str(root / name),
               "BENCH_MATRIX_LOCK_DIR": str(root / "machine-lock")}
        cluster.add_node(num_cpus=1, resources={"bench_matrix_timing": 1}, object_store_memory=memory,
                         env_vars=own)
    return cluster


def fixed_cost(project: Path, address: str) -> dict[str, float]:
    """Seconds the driver spends once per run: connecting to the cluster, probing every node."""
    from bench_matrix.executors.local import probe
    from bench_matrix.executors.ray_cluster import RayExecutor
    from bench_matrix.matrix.load import load_matrix
    from bench_matrix.plan import resolve
    from bench_matrix.registry import available
    from bench_matrix.workspace import Workspace

    ws = Workspace(project / "ws")
    plan = resolve(load_matrix(project / "m.yaml", backends=list(available())), ws, probe)
    begin = time.perf_counter()
    executor = RayExecutor(ws, address)
    connected = time.perf_counter()
    executor.probes(plan.matrix, [p for p in plan.cells if p.state != "invalid"])
    probed = time.perf_counter()
    executor.close()
    return {"connect_s": connected - begin, "probe_s": probed - connected}


def per_cell(facts: list[dict]) -> dict[str, float]:
    """Medians (and the least scheduling wait: no queue) of what Ray added to each cell, and its jobs."""
    def median(key: str) -> float:
        return statistics.median(f[key] for f in facts)

    return {"scheduled_min_s": min(f["scheduled_s"] for f in facts),
            "scheduled_median_s": median("scheduled_s"),
            "ship_median_s": median("ship_s"), "returned_median_s": median("returned_s"),
            "convert_median_s": median("convert_s"), "measure_median_s": median("measure_s")}


def estimate(cells: int, nodes: int, cell_s: float, measure_s: float, overhead_s: float,
             fixed_s: float) -> tuple[float, float]:
    """Wall seconds (conversions overlapping measurements, and not): once-per-run costs, then each node's
    share of the cells, one timing at a time; a node with a spare CPU converts the next cell while it
    measures one (a cell then takes max(measure, convert)), else a cell takes convert + measure."""
    per_node = math.ceil(cells / nodes)
    overlapped = max(measure_s, cell_s - measure_s) + overhead_s
    return fixed_s + per_node * overlapped, fixed_s + per_node * (cell_s + overhead_s)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=int, default=10, help="copies of the tiny model (2 cells each)")
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args()
    project = args.workdir or Path(tempfile.mkdtemp(prefix="ray-throughput-"))
    project.mkdir(parents=True, exist_ok=True)
    fuzz_cases.write_project(project)
    names = [f"m{i:02d}" for i in range(args.models)]
    (project / "m.yaml").write_text(onnx_matrix_text(names, ["fp32", "fp16"]))
    cells = 2 * args.models

    run_cli(project, "warm.sqlite")  # imports and caches warm, as on a machine that has run before
    local_s = run_cli(project, "local.sqlite")
    cluster = start_cluster(project / "nodes")
    try:
        run_cli(project, "ray-cold.sqlite", "--executor", "ray", "--address", cluster.address)
        cold = per_cell(ray_facts(project, "ray-cold.sqlite"))
        ray_s = run_cli(project, "ray.sqlite", "--executor", "ray", "--address", cluster.address)
        facts = per_cell(ray_facts(project, "ray.sqlite"))
        once = fixed_cost(project, cluster.address)
    finally:
        cluster.shutdown()
    overhead = facts["scheduled_min_s"] + facts["ship_median_s"] + facts["returned_median_s"]
    cell_s = facts["convert_median_s"] + facts["measure_median_s"]
    fixed = once["connect_s"] + once["probe_s"]
    figures = {"cells": cells, "local_wall_s": local_s, "ray_wall_s": ray_s,
               "local_cells_per_hour": round(cells * 3600 / local_s),
               "ray_cells_per_hour": round(cells * 3600 / ray_s), "per_cell": facts,
               "ship_median_cold_s": cold["ship_median_s"], "ray_overhead_per_cell_s": overhead,
               "once_per_run": once,
               "estimate_1000_cells_s": {str(n): estimate(1000, n, cell_s, facts["measure_median_s"],
                                                          overhead, fixed) for n in (10, 100)}}
    print(json.dumps(figures, indent=1))
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
