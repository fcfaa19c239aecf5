"""Test plugin backends for the conformance kit: one that keeps the contract (ONNX models on ONNX Runtime) and
one for each rule, each breaking it the way a real runtime would."""

from __future__ import annotations

import shutil
import threading
import time
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.plugin import Backend, ConvertRequest, Session, Support

FILE = "model.onnx"


class GoodOrt(Backend):
    """Copies the ONNX file and runs it on ONNX Runtime's CPU provider with exactly `threads` threads."""

    name = "good_ort"
    description = "keeps the contract"
    supports = (Support(("onnx",), ("none",), ("fp32",), ("cpu",)),)

    def versions(self) -> dict[str, str]:
        return {"onnxruntime": version("onnxruntime")}

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        shutil.copy2(request.source.path, request.out_dir / FILE)
        return {"file": FILE}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return OrtSession(self._session(artifact_dir / meta["file"], threads))

    def _session(self, path: Path, threads: int | None) -> Any:
        import onnxruntime as ort

        options = ort.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads = threads
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


class OrtSession(Session):
    """One InferenceSession fed the inputs by name; reports the threads it was given."""

    def __init__(self, session: Any):
        self._session = session

    def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self._session.run(None, prepared)

    def info(self) -> dict[str, Any]:
        return {"threads": self._session.get_session_options().intra_op_num_threads}


class Litters(GoodOrt):
    """Writes a log into the working directory, a marker into $HOME and a cache beside the source."""

    name = "litters"

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        Path("convert.log").write_text("converted\n")
        (Path.home() / ".zoo-marker").write_text("seen\n")
        request.source.path.with_suffix(".zoo-cache").write_text(str(time.time_ns()))
        return super().convert(request)


class IgnoresThreads(GoodOrt):
    """Never sets ONNX Runtime's threads: the session reports 0 (ONNX Runtime's own choice)."""

    name = "ignores_threads"

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return OrtSession(self._session(artifact_dir / meta["file"], None))


class Float64Out(GoodOrt):
    name = "float64_out"

    def load(self, *args: Any) -> Session:
        class Float64(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return [np.asarray(o, dtype=np.float64) for o in outputs]

        return Float64(super().load(*args)._session)


class DropsOutput(GoodOrt):
    name = "drops_output"

    def load(self, *args: Any) -> Session:
        class FirstOnly(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return [np.asarray(outputs[0], dtype=np.float32)]

        return FirstOnly(super().load(*args)._session)


class Squeezes(GoodOrt):
    """Squeezes every output: a batch of one loses its batch axis."""

    name = "squeezes"

    def load(self, *args: Any) -> Session:
        class Squeezed(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return [np.squeeze(np.asarray(o, dtype=np.float32)) for o in outputs]

        return Squeezed(super().load(*args)._session)


class NanOut(GoodOrt):
    name = "nan_out"

    def load(self, *args: Any) -> Session:
        class Nan(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return [np.log(-np.abs(np.asarray(o, dtype=np.float32)) - 1) for o in outputs]

        return Nan(super().load(*args)._session)


LOADS = [0]  # Drifts' loads so far in this process


class Drifts(GoodOrt):
    """fp16 by declaration, whose every load adds an offset of 5e-4 per load before it: within fp16's
    tolerance of the reference, but no two loads agree."""

    name = "drifts"
    supports = (Support(("onnx",), ("none",), ("fp16",), ("cpu",)),)

    def load(self, *args: Any) -> Session:
        LOADS[0] += 1
        offset = np.float32(5e-4 * LOADS[0])

        class Offset(OrtSession):
            def fetch(self, outputs: Any) -> list[np.ndarray]:
                return [np.asarray(o, dtype=np.float32) + offset for o in outputs]

        return Offset(super().load(*args)._session)


class AsyncExecute(GoodOrt):
    """execute starts the work on a thread (20 ms at least) and returns; fetch waits for it."""

    name = "async_execute"

    def load(self, *args: Any) -> Session:
        class Async(OrtSession):
            def execute(self, prepared: dict[str, np.ndarray]) -> Any:
                result: list[Any] = []

                def work() -> None:
                    time.sleep(0.02)
                    result.append(self._session.run(None, prepared))

                thread = threading.Thread(target=work)
                thread.start()
                return thread, result

            def fetch(self, outputs: Any) -> list[np.ndarray]:
                thread, result = outputs
                thread.join()
                return [np.asarray(o, dtype=np.float32) for o in result[0]]

        return Async(super().load(*args)._session)


class BadAnswers(GoodOrt):
    """Answers with values that are neither a reason nor None, names no library, accepts anything, and says
    its npu is a device bench-matrix does not know."""

    name = "bad_answers"
    supports = (Support(("onnx",), ("none",), ("fp32",), ("cpu", "npu")),)
    devices = {"npu": "npu"}

    def versions(self) -> dict[str, str]:
        return {}

    def probe(self, target: str, precision: str) -> str | None:
        return False if target == "npu" else None  # type: ignore[return-value]

    def option_reason(self, step: Any, source_format: str) -> str | None:
        return 0  # type: ignore[return-value]

    def invalid_reason(self, framework: str, strategy: str, precision: str, target: str) -> str | None:
        return None


PROBED: list[tuple[str, str]] = []  # NoDevice's probe questions so far in this process


class NoDevice(GoodOrt):
    """Runs on an NPU only, which this machine lacks."""

    name = "no_device"
    supports = (Support(("onnx",), ("none",), ("fp32",), ("npu",)),)

    def probe(self, target: str, precision: str) -> str | None:
        PROBED.append((target, precision))
        return "no NPU on this machine (the zoo's probe)"


class Refuses(GoodOrt):
    name = "refuses"

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        raise ValueError("this runtime cannot take the model")


class KeepsOutDir(GoodOrt):
    """Stores the absolute path of the file it wrote: the directory is renamed before loading."""

    name = "keeps_out_dir"

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        super().convert(request)
        return {"path": str(request.out_dir / FILE)}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return OrtSession(self._session(Path(meta["path"]), threads))


class PathInMeta(GoodOrt):
    name = "path_in_meta"

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        return {**super().convert(request), "written": request.out_dir}


# The zoo's entry points: name -> class; `unloadable` names a module that does not exist.
ZOO = {cls.name: f"plugin_conformance_zoo:{cls.__name__}" for cls in (
    GoodOrt, Litters, IgnoresThreads, Float64Out, DropsOutput, Squeezes, NanOut, Drifts, AsyncExecute,
    BadAnswers, NoDevice, Refuses, KeepsOutDir, PathInMeta)}
ZOO["unloadable"] = "plugin_conformance_zoo_missing:Backend"


def install(site: Path, more: dict[str, str]) -> None:
    """The zoo, and the backends `more` registers (name -> entry point), installed into `site` as pip would (a
    .dist-info with their entry points)."""
    dist = site / "bm_conformance_zoo-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: bm-conformance-zoo\nVersion: 0.1\n")
    entries = "".join(f"{name} = {value}\n" for name, value in {**ZOO, **more}.items())
    (dist / "entry_points.txt").write_text(f"[bench_matrix.backends]\n{entries}")

