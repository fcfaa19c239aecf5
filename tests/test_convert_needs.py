"""A Support's convert_needs: judged where the model is converted, not on a device that only runs it
(OpenVINO's int8 needs NNCF to quantise, not to run); NNCF's absence simulated by a None in sys.modules."""

from __future__ import annotations

import sys

from bench_matrix.jobs import ProbeJob
from bench_matrix.jobs.probe import probe
from bench_matrix.workspace import Workspace

INT8 = ("openvino", "onnx", "ptq_static", "int8", "cpu", "onnx", "{}", "")


def _skip(monkeypatch, tmp_path, measure_only: bool) -> str | None:
    monkeypatch.setitem(sys.modules, "nncf", None)  # importlib.util.find_spec("nncf") is None: not installed
    job = ProbeJob(Workspace(tmp_path), ("openvino",), (INT8,), measure_only=measure_only)
    return probe(job).rulings[INT8].skip


def test_a_device_runs_openvino_int8_without_nncf(monkeypatch, tmp_path):
    assert _skip(monkeypatch, tmp_path, measure_only=True) is None


def test_the_converting_machine_needs_nncf_for_openvino_int8(monkeypatch, tmp_path):
    assert _skip(monkeypatch, tmp_path, measure_only=False) == "needs nncf to convert ptq_static at int8, not installed"
