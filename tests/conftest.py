"""Shared fixtures: a tiny user project (model factory + weights, .npz dataset, matrix), the fitted tiny model as a
backend source with its reference outputs, and a CLI runner."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:
    from bench_matrix.sources import SourceModel

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))
import tiny_models  # noqa: E402

TINY_X = tiny_models.images(16, 2)  # the inputs the `reference` outputs belong to
# short windows and budgets, one process a cell: tests that judge timing, or a cell's processes, set their own
FAST_SETTINGS = ("settings: {window_s: 0.01, min_rounds: 2, timing_budget_s: 0.05, warmup_iterations: 2, "
                 "warmup_s: 0.0, batch_size: 8, timeout_s: 120, processes: 1}\n")
TWO_PROCESSES = ("processes: 1", "processes: 2")  # FAST_SETTINGS.replace(*TWO_PROCESSES): the default's 2
GPU_NOT_RUN = pytest.StashKey[str]()  # which gpu- and arm64-marked tests were deselected, and why
ARM64_OPT_IN = "opt-in: `pytest -m arm64` with the emulated arm64 board started (docs/devices.md §7)"


# the files taking 15 s or more in all, longest first (a timed run's --durations): pytest-xdist hands out
# whole files in collection order (the test command turns its own order off), and the longest should start
# first, or one worker ends minutes before the other; the files not named here follow them
LONGEST_FIRST = ("test_conformance", "test_cli_training", "test_cli_tensorflow", "test_closed_loop",
                 "test_torch_compile", "test_cli", "test_concurrent_runs", "test_ssh", "test_auto_matrix",
                 "test_tfmot_trainer", "test_remeasure", "test_ray", "test_history", "test_cli_tasks",
                 "test_fuzz_inputs", "test_forward_inputs", "test_open_axes", "test_rounds",
                 "test_verdict_cli", "test_openvino", "test_cache_keys", "test_transformer_int8")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files first (LONGEST_FIRST). Without an NVIDIA GPU (the first reason every GPU probe
    gives), the gpu-marked tests are deselected and reported in one line instead of skipped one by one; so
    are the arm64-marked ones unless -m names them."""
    from bench_matrix.hardware import no_gpu_reason

    rank = {name: place for place, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: a file's tests stay in order

    reasons = {"gpu": no_gpu_reason(),
               "arm64": None if "arm64" in (config.option.markexpr or "") else ARM64_OPT_IN}
    lines = [_deselect(config, items, marker, reason) for marker, reason in reasons.items() if reason]
    if not any(lines):
        return
    config.stash[GPU_NOT_RUN] = "\n".join(line for line in lines if line)
    if hasattr(config, "workeroutput"):  # a pytest-xdist worker: the controller prints the summary
        config.workeroutput["gpu_not_run"] = config.stash[GPU_NOT_RUN]


def _deselect(config: pytest.Config, items: list[pytest.Item], marker: str, reason: str) -> str:
    """The tests marked `marker` deselected, and the line saying so (empty where there were none)."""
    marked = [item for item in items if item.get_closest_marker(marker)]
    if not marked:
        return ""
    config.hook.pytest_deselected(items=marked)
    items[:] = [item for item in items if not item.get_closest_marker(marker)]
    return f"{len(marked)} tests marked {marker} not run (deselected): {reason}"


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: object, error: object) -> None:
    """pytest-xdist's controller, as a worker ends: keep the line its collection wrote."""
    if line := getattr(node, "workeroutput", {}).get("gpu_not_run"):
        node.config.stash[GPU_NOT_RUN] = line


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, config: pytest.Config) -> None:
    for line in config.stash.get(GPU_NOT_RUN, "").splitlines():
        terminalreporter.write_line(line)


@pytest.fixture(scope="session", autouse=True)
def own_timing_lock(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The suite's runs share a timing lock of their own (each pytest-xdist worker one), not the host's: a run
    measuring elsewhere on this machine must not make a test wait."""
    os.environ["BENCH_MATRIX_LOCK_DIR"] = str(tmp_path_factory.mktemp("timing-lock"))


@pytest.fixture
def tiny_project(tmp_path: Path) -> Path:
    """A directory holding tiny.pt (state_dict of tests/tiny_models.py:tiny), data.npz and nothing else."""
    import torch

    sys.path.insert(0, str(TESTS))
    from tiny_models import tiny

    torch.manual_seed(0)
    torch.save(tiny().state_dict(), tmp_path / "tiny.pt")
    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, size=(96, 16, 16, 3), dtype=np.uint8)
    y = np.stack([x[..., 0].mean(axis=(1, 2)), x[..., 1].mean(axis=(1, 2))], axis=1) / 255.0
    np.savez(tmp_path / "data.npz", x=x, y=y.astype(np.float32))
    return tmp_path


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> "SourceModel":
    """tiny_models.fitted() as a state_dict source: its outputs follow its input as PilotNet's do (a randomly
    initialised net outputs little but its biases, against which any precision or int8 check is vacuous)."""
    import torch

    from bench_matrix.sources import SourceModel
    from bench_matrix.tensors import TensorSpec

    path = tmp_path_factory.mktemp("source") / "tiny.pt"
    torch.save(tiny_models.fitted().state_dict(), path)
    return SourceModel(name="tiny", framework="pytorch", format="state_dict", path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                       inputs=(TensorSpec("input", tiny_models.INPUT_SHAPE),), factory="tiny_models:tiny",
                       python_path=(str(TESTS),))


@pytest.fixture(scope="module")
def reference(source: "SourceModel") -> np.ndarray:
    """The fitted tiny model's fp32 outputs on TINY_X."""
    import torch

    with torch.inference_mode():
        y = source.load()(torch.from_numpy(TINY_X)).numpy()
    assert y.std(axis=0).min() > 0.2  # the outputs do follow the input
    return y


def matrix_text(backends: list[str], strategies: list[str], precisions: list[str], targets: list[str],
                extra: str = "") -> str:
    return (f"models:\n  - {{name: tiny, framework: pytorch, factory: 'tiny_models:tiny', weights: tiny.pt, "
            f"python_path: ['{TESTS}']}}\n"
            f"dataset: {{npz: data.npz, split: {{train: 0.5, calibration: 0.25, test: 0.25}}}}\n"
            f"axes: {{backend: {backends}, strategy: {strategies}, precision: {precisions}, target: {targets}}}\n"
            + FAST_SETTINGS + extra)


@pytest.fixture
def onnx_project(tmp_path: Path) -> Path:
    """tiny.onnx (tests/fuzz_cases.py) and data.npz: for tests of how runs behave, not of what they convert;
    no process of its runs imports torch or TensorFlow (about 5 s a run instead of 15)."""
    import fuzz_cases

    return fuzz_cases.write_project(tmp_path)


def onnx_matrix_text(models: list[str], precisions: list[str], extra: str = "") -> str:
    """tiny.onnx under each name in `models` through ONNX Runtime on the CPU at `precisions` (fp32, fp16)."""
    entries = "".join(f"  - {{name: {name}, framework: onnx, file: tiny.onnx}}\n" for name in models)
    return ("models:\n" + entries
            + "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
            f"axes: {{backend: [onnxruntime], strategy: [none], precision: {precisions}, target: [cpu]}}\n"
            + FAST_SETTINGS + extra)


def install_slow_plugin(root: Path) -> dict[str, str]:
    """tests/plugin_slow.py installed as pip would (a .dist-info with its entry point); the CLI's env."""
    dist = root / "site" / "slow_ort-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: slow-ort\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bench_matrix.backends]\nslow_ort = plugin_slow:SlowOrtBackend\n")
    return {"PYTHONPATH": os.pathsep.join([str(root / "site"), str(TESTS), os.environ.get("PYTHONPATH", "")])}


def cli(project: Path, *args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run `bench-matrix` as a user would, in the project directory, with its own workspace."""
    return subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), *args],
                          cwd=project, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "COLUMNS": "200", **(env or {})})


def popen_cli(project: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    """`bench-matrix` started in the background; Ctrl-C (SIGINT) reaches it as a user's would, even when pytest
    itself was started in the background of a shell (which leaves SIGINT ignored, and children inherit that)."""
    return subprocess.Popen([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), *args],
                            cwd=project, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, **(env or {})},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
