"""`run --shard I/N`: a deterministic partition of the chosen cells by key; the shards' stores merged hold the
same records as one unsharded run."""

from __future__ import annotations

import json
import random
import sqlite3
from pathlib import Path

import pytest
from conftest import cli, onnx_matrix_text

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import UserError
from bench_matrix.selection import Shard

# two ONNX models at two precisions on the CPU, plus their CUDA cells: skipped here (no GPU) with the reason
MATRIX = onnx_matrix_text(["tiny", "twin"], ["fp32", "fp16"]).replace("target: [cpu]", "target: [cpu, cuda]")


def _plans(count: int) -> list[CellPlan]:
    return [CellPlan(Cell(f"m{i:02d}", "onnx", "onnxruntime", "none", "fp32", "cpu"), "run")
            for i in range(count)]


@pytest.mark.parametrize("count,shards", [(1, 1), (7, 3), (20, 4), (3, 5)])
def test_shards_partition_the_cells_evenly_whatever_their_order(count, shards):
    cells = _plans(count)
    mixed = random.Random(count).sample(cells, len(cells))
    parts = [Shard(i, shards).select(cells) for i in range(1, shards + 1)]
    assert [Shard(i, shards).select(mixed) for i in range(1, shards + 1)] == [
        [p for p in mixed if p in part] for part in parts]  # same cells, in the order given
    keys = [p.cell.key for part in parts for p in part]
    assert sorted(keys) == sorted(p.cell.key for p in cells)  # every cell in exactly one shard
    sizes = [len(part) for part in parts]
    assert max(sizes) - min(sizes) <= 1


@pytest.mark.parametrize("text", ["0/2", "3/2", "1/0", "2", "a/b", "-1/2", "1/2/3", ""])
def test_a_bad_shard_names_the_option_and_what_is_allowed(text):
    with pytest.raises(UserError, match=r"--shard .*give I/N.*1 <= I <= N"):
        Shard.parse(text)


def test_a_good_shard_parses():
    assert Shard.parse(" 2 / 5 ") == Shard(2, 5)


def test_cli_rejects_a_bad_shard_with_exit_2(onnx_project):
    (onnx_project / "m.yaml").write_text(MATRIX)
    out = cli(onnx_project, "run", "m.yaml", "--shard", "3/2")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "--shard 3/2: give I/N" in out.stderr


def _records(db: Path) -> list[tuple[str, str]]:
    with sqlite3.connect(db) as con:
        return sorted(con.execute("SELECT key, status FROM records").fetchall())


@pytest.mark.slow
def test_shards_merged_equal_one_unsharded_run(onnx_project):
    (onnx_project / "m.yaml").write_text(MATRIX)
    for args in (("--results", "all.sqlite"), ("--results", "s1.sqlite", "--shard", "1/2"),
                 ("--results", "s2.sqlite", "--shard", "2/2")):
        out = cli(onnx_project, "run", "m.yaml", *args)
        assert out.returncode == 0, out.stdout + out.stderr
    whole = _records(onnx_project / "all.sqlite")
    assert [s for _, s in whole].count("ok") == 4 and [s for _, s in whole].count("skipped") == 4
    first, second = _records(onnx_project / "s1.sqlite"), _records(onnx_project / "s2.sqlite")
    assert first and second and not set(first) & set(second)  # each cell recorded by one shard only

    merged = onnx_project / "merged.sqlite"
    out = cli(onnx_project, "merge", "s1.sqlite", "s2.sqlite", "--into", str(merged))
    assert out.returncode == 0, out.stdout + out.stderr
    assert _records(merged) == whole
    with sqlite3.connect(merged) as con:
        summaries = [json.loads(s) for (s,) in con.execute("SELECT summary FROM runs")]
    assert sorted(s["shard"] for s in summaries) == ["1/2", "2/2"]
