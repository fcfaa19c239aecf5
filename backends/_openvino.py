"""What the openvino backend needs of OpenVINO itself: its import with telemetry off, the devices it finds and
the precisions each computes in, and the properties a model is compiled with, read back once compiled."""

from __future__ import annotations

import importlib.util
import re
import sys
from typing import TYPE_CHECKING, Any

from bench_matrix.plugin import installed_versions

if TYPE_CHECKING:
    import openvino as ov

INSTALL = "pip install 'bench-matrix[openvino]'"
DEVICES = {"cpu": "CPU", "intel_gpu": "GPU", "intel_npu": "NPU"}  # target -> OpenVINO device
DEVICE_NAMES = {"CPU": "CPU", "GPU": "Intel GPU", "NPU": "Intel NPU"}
# OpenVINO's GPU and NPU plugins run Intel hardware only; what makes each device appear.
DEVICE_FIXES = {
    "GPU": "OpenVINO's GPU plugin runs Intel integrated and discrete GPUs through OpenCL: install Intel's "
           "compute runtime (intel-opencl-icd) and an OpenCL loader (ocl-icd-libopencl1); NVIDIA and AMD "
           "GPUs are not OpenVINO devices",
    "NPU": "OpenVINO's NPU plugin runs the NPU of Intel Core Ultra processors: install Intel's NPU driver "
           "(github.com/intel/linux-npu-driver), which creates /dev/accel/accel0",
}
CAPABILITIES = {"fp32": "FP32", "fp16": "FP16", "bf16": "BF16", "int8": "INT8"}  # OPTIMIZATION_CAPABILITIES
CPU_NEEDS = {"bf16": "AVX512_BF16 or AMX on x86", "fp16": "AMX-FP16 on x86, or ARMv8.2 FP16 on ARM"}
# INFERENCE_PRECISION_HINT per precision. Without it the CPU computes fp32 models in bf16 wherever it can (a
# GPU in fp16), so fp32 is asked for explicitly; int8 models compute their unquantised layers in f32.
HINTS = {"fp32": "f32", "int8": "f32", "bf16": "bf16", "fp16": "f16"}
OPTION_DEFAULTS = {"hint": "latency", "streams": 1, "pinning": True}
# What a compiled model reports, by the name the session records it under.
READ_BACK = {"execution_devices": "EXECUTION_DEVICES", "inference_precision": "INFERENCE_PRECISION_HINT",
             "performance_hint": "PERFORMANCE_HINT", "streams": "NUM_STREAMS",
             "threads": "INFERENCE_NUM_THREADS", "pinning": "ENABLE_CPU_PINNING"}


def openvino() -> Any:
    """The openvino module, imported with openvino_telemetry unimportable: neither OpenVINO nor NNCF starts
    its telemetry."""
    # `import openvino` (and `import nncf`) starts openvino_telemetry, which writes a client id to ~/intel and
    # sends usage events to Google Analytics unless a consent file there says no. Both libraries fall back to
    # a no-op stub when it cannot be imported; a None in sys.modules makes its import fail.
    if "openvino" not in sys.modules:
        sys.modules["openvino_telemetry"] = None  # type: ignore[assignment]
    import openvino

    return openvino


def openvino_version() -> str:
    return installed_versions("openvino").get("openvino", "(unknown version)")


def missing_reason() -> str | None:
    """Why OpenVINO cannot be imported here (found without importing it), or None. int8's NNCF converts and
    is not needed to run: the int8 Support's convert_needs names it."""
    if importlib.util.find_spec("openvino") is None:
        return f"openvino is not installed: {INSTALL}"
    return None


def device_reason(target: str, precision: str) -> str | None:
    """Why OpenVINO cannot run `precision` on the target's device here: the device is absent (with OpenVINO's
    words when its plugin cannot load), or its capabilities do not list the precision."""
    core = openvino().Core()
    device = DEVICES[target]
    if not any(found.split(".")[0] == device for found in core.available_devices):
        return _absent_reason(core, device)
    capabilities = list(core.get_property(device, "OPTIMIZATION_CAPABILITIES"))
    if CAPABILITIES[precision] in capabilities:
        return None
    needs = CPU_NEEDS.get(precision) if device == "CPU" else None
    return (f"{device_name(core, device)} has no {precision} in OpenVINO {openvino_version()}: the {device} "
            f"device's OPTIMIZATION_CAPABILITIES are {', '.join(capabilities)}"
            + (f" ({precision} needs {needs})" if needs else ""))


def _absent_reason(core: "ov.Core", device: str) -> str:
    try:
        core.get_versions(device)
    except RuntimeError as exc:  # the plugin's library cannot load (a missing OpenCL loader, say)
        said = [line for line in str(exc).splitlines() if line.strip()][-1]
        said = re.sub(r'"[^"]*/([^/"]+)"', r"\1", said)  # the library's file name, not its path
        return (f"OpenVINO {openvino_version()} cannot load its {device} plugin ({said}); "
                f"{DEVICE_FIXES[device]}")
    return (f"OpenVINO {openvino_version()} finds no {DEVICE_NAMES[device]}: Core().available_devices is "
            f"{core.available_devices}; {DEVICE_FIXES[device]}")


def device_name(core: "ov.Core", device: str) -> str:
    """The device's FULL_DEVICE_NAME where it reports one, else what OpenVINO calls it."""
    try:
        return str(core.get_property(device, "FULL_DEVICE_NAME")).strip()
    except RuntimeError:
        return DEVICE_NAMES[device]


def compile_config(core: "ov.Core", device: str, precision: str, options: dict[str, Any],
                   threads: int) -> dict[str, Any]:
    """The properties a model is compiled with: the precision hint, performance hint and streams, and on the
    CPU the threads and pinning; only those the device supports (a GPU has no thread count)."""
    options = {**OPTION_DEFAULTS, **options}
    wanted: dict[str, Any] = {"PERFORMANCE_HINT": options["hint"].upper(), "NUM_STREAMS": options["streams"]}
    if hint := precision_hint(core, device, precision):
        wanted["INFERENCE_PRECISION_HINT"] = hint
    if device == "CPU":
        wanted.update(INFERENCE_NUM_THREADS=threads, ENABLE_CPU_PINNING=options["pinning"])
    supported = core.get_property(device, "SUPPORTED_PROPERTIES")
    return {key: value for key, value in wanted.items() if key in supported}


def precision_hint(core: "ov.Core", device: str, precision: str) -> str | None:
    """The INFERENCE_PRECISION_HINT for `precision`; None for int8 on a device without FP32 (an NPU's float
    layers run in its own precision)."""
    if precision == "int8" and "FP32" not in core.get_property(device, "OPTIMIZATION_CAPABILITIES"):
        return None
    return HINTS[precision]


def in_force(compiled: "ov.CompiledModel") -> dict[str, Any]:
    """The properties the compiled model reports (those of READ_BACK its device knows), as JSON values."""
    found = {}
    for key, name in READ_BACK.items():
        try:
            value = compiled.get_property(name)
        except RuntimeError:  # a property this device does not report
            continue
        found[key] = value.get_type_name() if hasattr(value, "get_type_name") else _plain(value)
    return found


def _plain(value: Any) -> Any:
    """A property's value as JSON: numbers, strings and lists as they are, anything else as its text."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return str(value)
