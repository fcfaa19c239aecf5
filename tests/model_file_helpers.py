"""What the model-file tests share: sources of test files, hostile pickles and code, zip rewriting, and the
assertion that loading a file is refused with a message naming it."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any, Callable

import pytest
import torch

import tiny_models
from conftest import TESTS
from fuzz_cases import Payload

from bench_matrix.errors import UserError
from bench_matrix.sources import SourceModel
from bench_matrix.sources.onnx_file import load_onnx
from bench_matrix.tensors import TensorSpec


def pickle_payload(marker: Path) -> bytes:
    buffer = io.BytesIO()
    torch.save(Payload(marker), buffer)
    return buffer.getvalue()


def make_source(path: Path, fmt: str, framework: str = "pytorch", **extra: Any) -> SourceModel:
    return SourceModel(name="m", framework=framework, format=fmt, path=path, sha256="not checked here",
                       inputs=(TensorSpec("input", tiny_models.INPUT_SHAPE),), **extra)


def factory_source(path: Path, factory: str = "tiny_models:tiny", where: Path = TESTS) -> SourceModel:
    return make_source(path, "state_dict", factory=factory, python_path=(str(where),))


def refused(source: SourceModel, *expected: str) -> None:
    """Loading `source` raises a UserError whose message holds each expected text, and no unsafe advice."""
    with pytest.raises(UserError) as caught:
        load_source(source)
    message = str(caught.value)
    assert all(text in message for text in expected), message
    assert "weights_only=False" not in message and "Traceback" not in message


def load_source(source: SourceModel) -> Any:
    """The source's framework object; for ONNX, the model as bench-matrix reads it."""
    return load_onnx(source.path, source.label) if source.framework == "onnx" else source.load()


def rewrite_zip(src: Path, dst: Path, change: Callable[[str, bytes], bytes], extra: dict[str, bytes]) -> Path:
    """Copy a zip archive entry by entry through `change` (names below a torch archive's root folder),
    adding `extra` entries."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        root = zin.namelist()[0].split("/")[0] if src.suffix == ".pt2" else ""
        for info in zin.infolist():
            zout.writestr(info.filename, change(info.filename.removeprefix(f"{root}/"), zin.read(info)))
        for name, data in extra.items():
            zout.writestr(f"{root}/{name}", data)
    return dst


def payload_code(marker: Path) -> str:
    return f"__import__('pathlib').Path({str(marker)!r}).write_text('pwned')"
