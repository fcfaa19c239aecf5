"""ONNX Runtime's providers: which ones a target gets and with which options (TensorRT's engine cache, shape
profile and int8 calibration table inside the artifact), why this machine cannot run a target, TensorRT engines
built at conversion, and sessions whose input and output stay on the GPU."""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import Session, cuda_mismatch_reason, installed_versions, no_gpu_reason, \
    precision_reason

if TYPE_CHECKING:
    import onnxruntime
    from onnxruntime.quantization import CalibrationDataReader

PROVIDERS = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider",
             "tensorrt": "TensorrtExecutionProvider"}
# Every distribution that installs the `onnxruntime` module; whichever is installed is the one reported.
DISTRIBUTIONS = ("onnxruntime", "onnxruntime-gpu", "onnxruntime-directml", "onnxruntime-openvino")
CACHE_DIR = "trt_cache"  # inside the artifact: TensorRT's engines and profiles, and the int8 calibration table
# write_calibration_table writes calibration.json, calibration.flatbuffers and calibration.cache. With
# trt_int8_use_native_calibration_table off, the TensorRT provider reads the flatbuffers one (ReadDynamicRange in
# onnxruntime/core/providers/tensorrt/tensorrt_execution_provider_utils.h) from
# GetCachePath(trt_engine_cache_path, trt_int8_calibration_table_name): the name is relative to the cache path.
CALIBRATION_TABLE = "calibration.flatbuffers"
# The TensorRT provider appends these to an engine's file name when it sets the builder's FP16 or INT8 flag, and
# leaves the flag off (with a warning only) where the GPU lacks fast fp16 or int8: the file names tell what it built.
ENGINE_PRECISION = {"fp16": "_fp16", "int8": "_int8"}
Provider = str | tuple[str, dict[str, str]]
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_FAILED = re.compile(r"Failed to (load|create) .*")
_MISSING = re.compile(r"(\S+\.so[.\d]*): cannot open shared object file")
TENSORRT_LIBRARIES = ("libnvinfer.", "libnvinfer_plugin.", "libnvonnxparser.")  # the provider's needs
# fp32 means IEEE fp32: the CUDA provider's use_tf32 defaults to 1, and then its fp32 Conv and MatMul round
# their inputs to TF32 (10 mantissa bits, as fp16). Seen on an H100: "fp32" outputs 1e-3 from the CPU's, as
# far as fp16's.
CUDA_OPTIONS = {"use_tf32": "0"}
ORT_DTYPES = ("float32", "float16", "float64", "int64", "int32", "int16", "int8", "uint8", "bool")


@dataclass(frozen=True)
class EngineSpec:
    """What the TensorRT provider is told about one artifact's engines."""

    inputs: tuple[tuple[str, tuple[int, ...]], ...]  # each graph input's name and sample shape, in order
    max_batch: int | None  # profile batches 1..max_batch; None: the model's batch size is fixed (no profile)
    cache_dir: Path
    calibrated: bool  # cache_dir holds an int8 calibration table
    timing_dir: Path | None = None  # TensorRT's timing cache while engines are built; None at load

    @classmethod
    def at_load(cls, artifact_dir: Path, meta: dict[str, Any]) -> "EngineSpec":
        """The spec of an artifact in its final place: the cache directory found relative to `artifact_dir`."""
        if "tensorrt" not in meta:
            raise RuntimeError(f"{artifact_dir} was converted for TensorRT before engines were built at conversion "
                               f"(its metadata has no 'tensorrt' entry): delete it so that it is converted again")
        trt = meta["tensorrt"]
        inputs = tuple((name, tuple(shape)) for name, shape in trt["inputs"])
        return cls(inputs, trt["max_batch"], artifact_dir / CACHE_DIR, trt["calibrated"])

    def to_meta(self) -> dict[str, Any]:
        """What `at_load` needs, as JSON (paths are not kept: the artifact moves after conversion)."""
        return {"inputs": [[name, list(shape)] for name, shape in self.inputs], "max_batch": self.max_batch,
                "calibrated": self.calibrated}


def profile_reason(inputs: Sequence[tuple[str, Sequence[int | None]]]) -> str | None:
    """Why the TensorRT provider's shape profiles cannot name these inputs, or None: a name holding ':' or ','
    (where the profile strings split) or a free axis (an engine is built for fixed sample shapes)."""
    for name, shape in inputs:
        if ":" in name or "," in name:
            return (f"the input {name!r} cannot be named in the TensorRT provider's shape profiles, which split "
                    f"at ':' and ','; rename the model's input")
        if None in shape:
            return (f"the input {name!r} has a free axis (shape {tuple(shape)} per sample) and the TensorRT "
                    f"engines are built for fixed sample shapes; declare its length in the model's `inputs:`")
    return None


def feed_dtypes(session: "onnxruntime.InferenceSession") -> dict[str, np.dtype]:
    """The numpy dtype each graph input of `session` takes ('tensor(float)' -> float32), where numpy has one."""
    found = {}
    for value in session.get_inputs():
        name = value.type.removeprefix("tensor(").removesuffix(")")
        name = {"float": "float32", "double": "float64"}.get(name, name)
        if name in ORT_DTYPES:
            found[value.name] = np.dtype(name)
    return found


def providers(target: str, precision: str, spec: EngineSpec | None = None) -> list[Provider]:
    """The provider list of a session for `target`: nodes a GPU provider lacks run on the next one."""
    if target == "cpu":
        return [PROVIDERS["cpu"]]
    gpu: list[Provider] = [(PROVIDERS["cuda"], dict(CUDA_OPTIONS)), PROVIDERS["cpu"]]
    if target == "cuda":
        return gpu
    if spec is None:
        raise ValueError("a TensorRT session needs the artifact's EngineSpec (cache directory, shape profile)")
    return [(PROVIDERS["tensorrt"], tensorrt_options(precision, spec)), *gpu]


def tensorrt_options(precision: str, spec: EngineSpec) -> dict[str, str]:
    """TensorrtExecutionProvider options, as the strings ONNX Runtime's Python API passes on."""
    options = {"trt_fp16_enable": str(precision == "fp16"), "trt_int8_enable": str(precision == "int8"),
               "trt_engine_cache_enable": "True", "trt_engine_cache_path": str(spec.cache_dir),
               "trt_timing_cache_enable": str(spec.timing_dir is not None)}
    if spec.timing_dir is not None:
        options["trt_timing_cache_path"] = str(spec.timing_dir)
    if spec.calibrated:
        options |= {"trt_int8_calibration_table_name": CALIBRATION_TABLE,
                    "trt_int8_use_native_calibration_table": "False"}
    if spec.max_batch is not None:  # "name:1x3x66x200,ids:1x128"; opt = max_batch, where a batch does the most work
        options |= {"trt_profile_min_shapes": _profile(spec.inputs, 1),
                    "trt_profile_opt_shapes": _profile(spec.inputs, spec.max_batch),
                    "trt_profile_max_shapes": _profile(spec.inputs, spec.max_batch)}
    return options


def _profile(inputs: Sequence[tuple[str, Sequence[int]]], batch: int) -> str:
    """A shape profile entry for every input at `batch`: 'image:8x3x66x200,ids:8x128'."""
    return ",".join(f"{name}:{'x'.join(str(d) for d in (batch, *shape))}" for name, shape in inputs)


def package() -> str:
    """The installed ONNX Runtime distribution, e.g. 'onnxruntime-gpu 1.31.1', or a warning that several are."""
    found = [" ".join(item) for item in installed_versions(*DISTRIBUTIONS).items()]
    if len(found) > 1:  # each overwrites the other's files, so which providers exist depends on the install order
        return f"{' and '.join(found)} (both install the onnxruntime module: uninstall all of them, then install one)"
    return found[0] if found else "onnxruntime"


def probe_reasons(target: str, precision: str) -> list[str]:
    """Why this machine cannot run `target` (cuda or tensorrt) at `precision`; empty when it can."""
    import onnxruntime as ort

    # onnxruntime.cuda_version: the CUDA version a GPU build targets, from capi/build_and_package_info.py
    # (onnxruntime_validation.get_package_name_and_version_info); empty in CPU builds.
    built_for = getattr(ort, "cuda_version", "") or None
    reasons = gpu_reasons(target, precision, ort.get_available_providers(), built_for)
    if not reasons:  # everything else is in place: can the providers' own libraries load?
        wanted = [PROVIDERS[target], PROVIDERS["cuda"]] if target == "tensorrt" else [PROVIDERS[target]]
        reasons = list(dict.fromkeys(r for p in wanted if (r := library_reason(p, built_for))))
    return reasons


@functools.cache
def library_reason(provider: str, built_for: str | None) -> str | None:
    """The library that ONNX Runtime's shared library for `provider` links and that cannot be found here, even after
    `preload_libraries`, as a reason with what to install; None when it loads (or cannot be checked)."""
    import onnxruntime as ort

    name = {PROVIDERS["cuda"]: "cuda", PROVIDERS["tensorrt"]: "tensorrt"}[provider]
    library = Path(ort.__file__).parent / "capi" / f"libonnxruntime_providers_{name}.so"
    if not library.is_file():
        return None
    # In a child process: loading it maps the CUDA libraries, which this (planning) process does not need.
    code = (f"import ctypes, importlib, sys, onnxruntime; importlib.import_module({__name__!r})"
            f".preload_libraries(onnxruntime); ctypes.CDLL(sys.argv[1])")
    try:
        done = subprocess.run([sys.executable, "-c", code, str(library)], capture_output=True, text=True,
                              timeout=120, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    missing = _MISSING.search(done.stderr)
    return missing_library_reason(provider, missing.group(1), built_for) if missing else None


def missing_library_reason(provider: str, soname: str, built_for: str | None) -> str:
    """What to install when `provider`'s library cannot find `soname` (e.g. 'libnvinfer.so.10')."""
    cuda = (built_for or "").split(".")[0]
    if soname.startswith("libcuda.so"):
        fix = "it is the NVIDIA driver's library: install the driver"
    elif soname.startswith(("libnvinfer", "libnvonnxparser")):
        release = soname.rsplit(".so.", 1)[-1]
        fix = f"it is TensorRT {release}'s: pip install 'tensorrt-cu{cuda}-libs=={release}.*'"
    elif soname.startswith("libcudnn"):
        fix = "it is cuDNN's: pip install 'onnxruntime-gpu[cudnn]' (the same onnxruntime-gpu version)"
    else:
        fix = (f"it is one of CUDA {built_for}'s: pip install 'onnxruntime-gpu[cuda,cudnn]' (the same "
               f"onnxruntime-gpu version)")
    return f"{package()} has {provider}, but its library needs {soname}, which is not installed: {fix}"


def gpu_reasons(target: str, precision: str, available: list[str], built_for: str | None) -> list[str]:
    """Each missing piece once, in order: GPU, provider, driver for the build's CUDA, GPU generation."""
    wanted = PROVIDERS[target]
    reasons = [reason] if (reason := no_gpu_reason()) else []
    if wanted not in available:
        reasons.append(f"the installed {package()} has no {wanted} (it has {', '.join(available)}); "
                       f"install onnxruntime-gpu in its place")
    if reason := cuda_mismatch_reason(package().split()[0], built_for):
        reasons.append(reason)
    if reason := precision_reason(precision, f"{precision} on {wanted}"):
        reasons.append(reason)
    return reasons


def fallback_message(target: str, got: list[str], available: list[str], said: Sequence[str] = ()) -> str:
    """Why a session that should run on `target`'s provider runs on `got` instead, and what to fix; `said` is what
    ONNX Runtime logged about it (`ort_said`)."""
    wanted = PROVIDERS[target]
    why = (f"{package()} has {wanted} but it failed to initialise: check that the CUDA, cuDNN and TensorRT "
           f"libraries match its build" if wanted in available
           else f"{package()} has no {wanted}: install onnxruntime-gpu in its place")
    return (f"asked ONNX Runtime for {wanted} (target {target}) but the session runs on {got}, as ONNX Runtime "
            f"falls back silently; {why}{_quoted(said)}")


def ort_said(log: list[str]) -> list[str]:
    """ONNX Runtime's own words on a provider that failed ("Failed to load library …: libcublas.so.13 …",
    "Failed to create CUDAExecutionProvider. Require …"), from its native log lines, each once."""
    found = (_FAILED.search(_ANSI.sub("", line)) for line in log)
    return list(dict.fromkeys(m.group(0).strip() for m in found if m))


def _quoted(said: Sequence[str]) -> str:
    return f"; ONNX Runtime said: {' | '.join(said)}" if said else ""


@contextmanager
def native_log() -> Iterator[list[str]]:
    """Collects what native code writes to stderr while inside (ONNX Runtime's C++ logger writes there, not through
    Python) into the yielded list of lines, and passes it on to stderr unchanged."""
    said: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as log:
        os.dup2(log.fileno(), 2)
        try:
            yield said
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            log.seek(0)
            text = log.read()
            os.write(2, text)
            said.extend(text.decode(errors="replace").splitlines())


def preload_libraries(ort: Any) -> None:
    """Load the CUDA, cuDNN and TensorRT libraries that pip packages installed (nvidia-*, tensorrt-cu*-libs), which
    the loader does not search, so that the GPU providers' own libraries find them by name."""
    if hasattr(ort, "preload_dlls"):  # ONNX Runtime 1.21+: CUDA and cuDNN from the nvidia pip packages
        ort.preload_dlls()
    found = importlib.util.find_spec("tensorrt_libs")  # TensorRT's pip wheels, as `import tensorrt` loads them
    for folder in (found.submodule_search_locations or []) if found else []:
        for library in sorted(Path(folder).glob("lib*.so.*")):
            if library.name.startswith(TENSORRT_LIBRARIES):
                try:
                    ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
                except OSError as error:
                    print(f"Failed to load {library}: {error}")


def open_session(model: Path, target: str, precision: str, threads: int, spec: EngineSpec | None = None,
                 profile_prefix: str | None = None) -> "onnxruntime.InferenceSession":
    """A session on `target`'s provider, or RuntimeError when ONNX Runtime fell back to another one; with
    `profile_prefix`, profiling from its creation, into that file's folder."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    if profile_prefix:
        options.enable_profiling, options.profile_file_prefix = True, profile_prefix
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    wanted = PROVIDERS[target]
    # enable_fallback=0: ONNX Runtime would otherwise retry a failed provider on the next ones, at session creation
    # and again when a run raises EPFail (InferenceSession.run), and a cell would time another provider unnoticed.
    log: list[str] = []
    try:
        with native_log() as log, redirect_stdout(sys.stderr):  # preload_dlls prints what it could not load
            if target != "cpu":
                preload_libraries(ort)
            session = ort.InferenceSession(str(model), options, providers=providers(target, precision, spec),
                                           enable_fallback=0)
    except Exception as error:  # ORT raises its own Fail and EPFail types
        if target == "cpu":
            raise
        raise RuntimeError(f"ONNX Runtime could not open a session on {wanted} (target {target}): "
                           f"{str(error).strip()}{_quoted(ort_said(log))}") from error
    if session.get_providers()[0] != wanted:
        raise RuntimeError(fallback_message(target, session.get_providers(), ort.get_available_providers(),
                                            ort_said(log)))
    if target != "cpu" and (in_force := cuda_options(session)) != CUDA_OPTIONS:
        raise RuntimeError(f"ONNX Runtime's {PROVIDERS['cuda']} runs with {in_force}, not {CUDA_OPTIONS}: "
                           f"its fp32 would not be IEEE fp32")
    return session


def cuda_options(session: "onnxruntime.InferenceSession") -> dict[str, str]:
    """The CUDA provider's options in force in `session` that bench-matrix sets (CUDA_OPTIONS' keys); none
    without that provider."""
    if PROVIDERS["cuda"] not in session.get_providers():
        return {}
    in_force = session.get_provider_options()[PROVIDERS["cuda"]]
    return {key: in_force.get(key, "unset") for key in CUDA_OPTIONS}


def write_calibration_table(model: Path, reader: "CalibrationDataReader", method: str, cache_dir: Path) -> int:
    """Calibrate the fp32 `model` on the CPU with ONNX Runtime's calibrator `method` (MinMax or Percentile) and
    write the table the TensorRT provider reads into cache_dir; returns how many tensors it ranges."""
    from onnxruntime.quantization import CalibrationMethod, create_calibrator
    from onnxruntime.quantization import write_calibration_table as write_tables

    with tempfile.TemporaryDirectory(prefix="bench-matrix-trt-calibration-") as tmp:
        copy = Path(tmp) / model.name  # the calibrator writes beside the model it reads
        shutil.copyfile(model, copy)
        # symmetric: write_calibration_table keeps max(highest, lowest) of each tensor, which TensorRT applies as
        # the range -value..value, so the range must be symmetric about zero already.
        calibrator = create_calibrator(copy, augmented_model_path=str(Path(tmp) / "augmented.onnx"),
                                       calibrate_method=getattr(CalibrationMethod, method),
                                       providers=[PROVIDERS["cpu"]], extra_options={"symmetric": True})
        calibrator.collect_data(reader)
        ranges = calibrator.compute_data()
        write_tables(ranges, dir=tmp)
        shutil.copyfile(Path(tmp) / CALIBRATION_TABLE, cache_dir / CALIBRATION_TABLE)
    return len(ranges.data)


def build_engines(model: Path, precision: str, threads: int, spec: EngineSpec, feeds: list[dict[str, np.ndarray]]
                  ) -> list[str]:
    """Build the TensorRT engines into spec.cache_dir by running `model` once per feed; their file names."""
    session = open_session(model, "tensorrt", precision, threads, spec)
    for feed in feeds:
        session.run(None, feed)
    engines = sorted(p.name for p in spec.cache_dir.glob("*.engine"))
    if not engines:
        raise RuntimeError(f"the TensorRT provider wrote no engine for {model.name} into {spec.cache_dir}: TensorRT "
                           f"takes none of its nodes, so the cell would measure the CUDA provider instead")
    mark = ENGINE_PRECISION.get(precision)
    if mark and (plain := [e for e in engines if mark not in e]):
        raise RuntimeError(f"TensorRT built {', '.join(plain)} without its {precision} flag: the provider leaves "
                           f"fp16 and int8 off where the GPU lacks fast support for them (ONNX Runtime's warnings "
                           f"say so); run this cell on a GPU that has it")
    return engines


class DeviceSession(Session):
    """A session whose inputs are copied to the device once (prepare) and whose outputs stay there until fetch."""

    def __init__(self, session: "onnxruntime.InferenceSession", feeds: dict[str, str], device: str):
        self._session = session
        self._run = session.run_with_iobinding
        self._feeds = feeds  # source input name -> graph input name
        self._dtypes = feed_dtypes(session)
        self._outputs = [value.name for value in session.get_outputs()]
        self._device = device
        self.quantization: dict[str, Any] | None = None  # how the model was quantised (the backend sets it)

    def prepare(self, inputs: dict[str, np.ndarray]) -> "onnxruntime.IOBinding":
        import onnxruntime as ort

        binding = self._session.io_binding()
        for name, graph in self._feeds.items():
            array = np.ascontiguousarray(inputs[name], dtype=self._dtypes.get(graph))
            binding.bind_ortvalue_input(graph, ort.OrtValue.ortvalue_from_numpy(array, self._device, 0))
        for output in self._outputs:
            binding.bind_output(output, self._device, 0)
        binding.synchronize_inputs()  # the copies have landed before anything is timed
        return binding

    def execute(self, prepared: "onnxruntime.IOBinding") -> "onnxruntime.IOBinding":
        # Run (which run_with_iobinding calls) ends by synchronising every provider's stream with the host
        # (cudaStreamSynchronize for CUDA) unless the run option disable_synchronize_execution_providers is "1"
        # (include/onnxruntime/core/session/onnxruntime_run_options_config_keys.h): it returns with the work done.
        self._run(prepared)
        return prepared

    def fetch(self, outputs: "onnxruntime.IOBinding") -> list[np.ndarray]:
        return [np.asarray(out, dtype=np.float32) for out in outputs.copy_outputs_to_cpu()]

    def info(self) -> dict[str, Any]:
        return {"providers": self._session.get_providers(),
                "threads": self._session.get_session_options().intra_op_num_threads,
                "io_binding": f"{self._device}:0", **cuda_options(self._session),
                **({"quantization": self.quantization} if self.quantization else {})}
