"""Generators of broken and hostile model files (PyTorch, ONNX, Keras) for test_fuzz_inputs.py, each with
what its error message must name; seeded. Run as a script, it builds the files of one framework."""

from __future__ import annotations

import io
import json
import os
import pickle
import sys
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fuzz_cases import Case, Payload, SECRET, SEED, TESTS, markers, onnx_model

def rezip(data: bytes, replace: dict[str, Callable[[bytes], bytes]], add: dict[str, bytes] | None = None
          ) -> bytes:
    """A copy of zip `data` with the members ending in a key of `replace` rewritten, and `add` appended."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as source, zipfile.ZipFile(out, "w") as target:
        for info in source.infolist():
            member = source.read(info.filename)
            for suffix, change in replace.items():
                member = change(member) if info.filename.endswith(suffix) else member
            target.writestr(info, member)
        prefix = source.namelist()[0].split("/")[0]
        for name, member in (add or {}).items():
            target.writestr(f"{prefix}/{name}", member)
    return out.getvalue()


def torch_bytes(obj: Any) -> bytes:
    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def torchscript(module: Any = None) -> bytes:
    import torch
    from tiny_models import tiny

    buffer = io.BytesIO()
    torch.jit.save(torch.jit.script(module or tiny().eval()), buffer)
    return buffer.getvalue()


def exported() -> bytes:
    import torch
    from tiny_models import tiny

    buffer = io.BytesIO()
    torch.export.save(torch.export.export(tiny().eval(), (torch.rand(1, 3, 16, 16),)), buffer)
    return buffer.getvalue()


def file_writer(marker: Path) -> bytes:
    """TorchScript whose forward writes `marker` (aten::save): code a model file carries."""
    import torch
    from tiny_models import tiny

    class Writer(torch.nn.Module):
        def __init__(self, path: str):
            super().__init__()
            self.path, self.net = path, tiny().eval()

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            torch.save(x, self.path)
            return self.net(x)

    return torchscript(Writer(str(marker)))


def pickled_weight(config: bytes) -> bytes:
    entries = json.loads(config)
    entries["config"]["0.weight"]["use_pickle"] = True
    return json.dumps(entries).encode()


def opaque_constant(_config: bytes) -> bytes:
    meta = {"path_name": "opaque_obj_0", "is_param": False, "use_pickle": True, "tensor_meta": None}
    return json.dumps({"config": {"evil": meta}}).encode()


def hostile_pt2(project: Path, marker: str) -> bytes:
    payload = Payload(markers(project) / marker)
    if marker == "pt2_weight":
        return rezip(exported(), {"model_weights_config.json": pickled_weight,
                                  "weights/weight_0": lambda _: torch_bytes(payload)})
    return rezip(exported(), {"model_constants_config.json": opaque_constant},
                 {"data/constants/opaque_obj_0": pickle.dumps(payload)})


def hostile_torchscript(project: Path) -> bytes:
    payload = zipfile.ZipFile(io.BytesIO(torch_bytes(Payload(markers(project) / "ts_pickle"))))
    return rezip(torchscript(), {"/data.pkl": lambda _: payload.read(next(n for n in payload.namelist()
                                                                         if n.endswith("data.pkl")))})


def mismatched_weights() -> bytes:
    import torch

    return torch_bytes(torch.nn.Linear(3, 2).state_dict())


FACTORIES = ("def raises():\n    raise RuntimeError('boom from the factory')\n\n\n"
             "def nothing():\n    return None\n")


def model_file(name: str, content: Callable[[Path], bytes], framework: str = "pytorch"
               ) -> Callable[[Path], dict]:
    def build(project: Path) -> dict[str, Any]:
        (project / "models").mkdir(exist_ok=True)
        (project / "models" / name).write_bytes(content(project))
        return {"framework": framework, "file": f"models/{name}"}
    return build


def factory(name: str, weights: Callable[[Path], bytes] | None = None) -> Callable[[Path], dict]:
    def build(project: Path) -> dict[str, Any]:
        (project / "pkg").mkdir(exist_ok=True)
        (project / "pkg" / "fuzz_factory.py").write_text(FACTORIES)
        file = project / (f"{name}.pt" if weights else "tiny.pt")
        if weights:
            file.write_bytes(weights(project))
        return {"framework": "pytorch", "factory": "tiny_models:tiny" if weights else name,
                "weights": file.name, "python_path": ["pkg", str(TESTS)]}
    return build


def half(make: Callable[[], bytes]) -> Callable[[Path], bytes]:
    def content(_project: Path) -> bytes:
        data = make()
        return data[: len(data) // 2]
    return content


def torch_model_cases() -> list[Case]:
    """PyTorch model files: broken, of another format, and hostile (pickles, code); needs torch."""
    files = {  # file name -> (content, marker)
        "onnx_inside.pt": (lambda _p: onnx_model(), None),
        "pickled_module.pt": (lambda p: torch_bytes(Payload(markers(p) / "pickled")), "pickled"),
        "ts_hostile.pt": (hostile_torchscript, "ts_pickle"),
        "ts_writer.pt": (lambda p: file_writer(markers(p) / "ts_writer"), "ts_writer"),
        "pt2_weight.pt2": (lambda p: hostile_pt2(p, "pt2_weight"), "pt2_weight"),
        "pt2_constant.pt2": (lambda p: hostile_pt2(p, "pt2_constant"), "pt2_constant"),
        "pt2_truncated.pt2": (half(exported), None),
    }
    weights = {
        "weights_hostile": (lambda p: torch_bytes({"0.weight": Payload(markers(p) / "weights")}), "weights"),
        "weights_mismatch": (lambda _p: mismatched_weights(), None),
        "weights_truncated": (lambda p: (p / "tiny.pt").read_bytes()[:500], None),
    }
    return ([Case(f"file:{name}", model_file(name, content), ((name,),), marker)
             for name, (content, marker) in files.items()]
            + [Case(f"weights:{name}", factory(name, content), ((f"{name}.pt",),), marker)
               for name, (content, marker) in weights.items()]
            + [Case("factory:raises", factory("fuzz_factory:raises"),
                    (("fuzz_factory:raises",), ("boom from the factory",))),
               Case("factory:returns_none", factory("fuzz_factory:nothing"), (("fuzz_factory:nothing",),))])


def external(location: Callable[[Path], str], setup: Callable[[Path], None] = lambda _p: None):
    def content(project: Path) -> bytes:
        (project / "secret").write_bytes(SECRET)
        setup(project / "models")
        return onnx_model(location(project))
    return content


def onnx_and_keras_cases() -> list[Case]:
    """ONNX files (broken, external data outside the model's folder) and Keras files (see build_keras)."""
    onnx_files = {
        "onnx_random.onnx": lambda _p: np.random.default_rng(SEED).bytes(2000),
        "onnx_empty.onnx": lambda _p: b"",
        "onnx_truncated.onnx": lambda _p: onnx_model()[:100],
        "ext_dotdot.onnx": external(lambda _p: "../secret"),
        "ext_absolute.onnx": external(lambda p: str(p / "secret")),
        "ext_symlink.onnx": external(lambda _p: "ext_link.bin",
                                     lambda m: (m / "ext_link.bin").symlink_to("../secret")),
        "ext_missing.onnx": external(lambda _p: "ext_missing.bin"),
        "ext_fifo.onnx": external(lambda _p: "ext_pipe.bin", lambda m: os.mkfifo(m / "ext_pipe.bin")),
    }
    cases = [Case(f"onnx:{name}", model_file(name, content, "onnx"), ((name,),))
             for name, content in onnx_files.items()]
    keras = {"lambda.keras": "lambda_keras", "lambda.h5": "lambda_h5", "writer_savedmodel": "savedmodel",
             "truncated.keras": None}
    return cases + [Case(f"keras:{name}", lambda _p, n=name: {"framework": "tensorflow",
                                                              "file": f"models/{n}"}, ((name,),), marker)
                    for name, marker in keras.items()]


def build_torch(project: Path) -> None:
    """tiny.pt and the files of every PyTorch case in `project`; prints their model entries as JSON."""
    import torch
    from tiny_models import tiny

    torch.save(tiny().state_dict(), project / "tiny.pt")
    print(json.dumps({case.id: case.build(project) for case in torch_model_cases()}))


def build_keras(project: Path) -> None:
    """Keras files: Lambda layers whose bytecode writes a marker (.keras, .h5), a SavedModel whose graph
    writes one (tf.io.write_file), a truncated .keras. Each payload is seen to work; its marker is removed."""
    out, marks = project / "models", markers(project)
    out.mkdir(exist_ok=True)
    os.environ["TF_USE_LEGACY_KERAS"] = "1"
    import tensorflow as tf
    import tf_keras as k

    def model(layer: Any) -> Any:
        return k.Sequential([k.layers.Input((16, 16, 3)), layer, k.layers.GlobalAveragePooling2D(),
                             k.layers.Dense(2)])

    for suffix in ("keras", "h5"):
        marker = marks / f"lambda_{suffix}"
        code = f"lambda x: (__import__('pathlib').Path({str(marker)!r}).write_text('x'), x)[1]"
        model(k.layers.Lambda(eval(code))).save(out / f"lambda.{suffix}")
        marker.unlink()  # written when the model was built: the bytecode is live

    class Writer(k.layers.Layer):
        def call(self, x: Any) -> Any:
            tf.io.write_file(str(marks / "savedmodel"), "pwned")
            return x

    model(Writer()).save(out / "writer_savedmodel", save_format="tf")
    k.models.load_model(out / "writer_savedmodel", compile=False)(np.zeros((1, 16, 16, 3), np.float32))
    (marks / "savedmodel").unlink()  # written by the reloaded graph: the payload is live
    model(k.layers.Activation("relu")).save(out / "plain.keras")
    data = (out / "plain.keras").read_bytes()
    (out / "truncated.keras").write_bytes(data[: len(data) // 2])


if __name__ == "__main__":  # run by test_fuzz_inputs.py in children: torch.export is not thread-safe
    {"torch": build_torch, "keras": build_keras}[sys.argv[1]](Path(sys.argv[2]))
