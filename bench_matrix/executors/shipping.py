"""Files that travel to another machine (a Ray node, an SSH device): packed as tar bytes keyed by their
content, unpacked once per key into that machine's workspace, and the paths in jobs and results rewritten."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import shutil
import tarfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from bench_matrix.workspace import Workspace

SHIPPED = "shipped"  # the folder of a workspace that holds what was shipped to it, by content key


def shipped_folder(ws: Workspace, key: str) -> Path:
    """Where content `key` lies once unpacked in a workspace."""
    return ws.root / SHIPPED / key


def pack(path: Path, beside: Sequence[Path] = (), keep: Callable[[str], bool] = lambda name: True
         ) -> tuple[str, bytes]:
    """A file or folder (its files `keep` accepts), with the files `beside` it that it reads (an ONNX model's
    external data), as tar bytes without times or owners (same content, same bytes), and their SHA-256."""
    def bare(info: tarfile.TarInfo) -> tarfile.TarInfo | None:
        inside = info.name.split("/")
        return _bare(info) if len(inside) != 2 or keep(inside[1]) else None

    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", format=tarfile.GNU_FORMAT) as tar:
        tar.add(path, arcname=path.name, filter=bare)
        for extra in beside:
            tar.add(extra, arcname=str(extra.relative_to(path.parent)), filter=_bare)
    data = buffer.getvalue()
    return hashlib.sha256(data).hexdigest(), data


def _bare(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
    return info


def extract(data: bytes, final: Path, ws: Workspace) -> None:
    """Tar bytes unpacked into the folder `final` of `ws`, which appears whole or not at all."""
    tmp = ws.partial(final)
    tmp.mkdir()
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        if hasattr(tarfile, "data_filter"):
            tar.extractall(tmp, filter="data")
        else:
            tar.extractall(tmp, members=_inside(tar))
    try:
        tmp.rename(final)
    except OSError:  # another job on this machine unpacked it first
        shutil.rmtree(tmp, ignore_errors=True)


def _inside(tar: tarfile.TarFile) -> list[tarfile.TarInfo]:
    """The pack's members, each a file or folder inside it, else refused: what the `data` filter checks where
    Python has one (3.11.4 and newer; Debian bookworm's Python, a Raspberry Pi's, is 3.11.2)."""
    members = tar.getmembers()
    for member in members:
        outside = member.name.startswith("/") or ".." in member.name.split("/")
        if outside or not (member.isfile() or member.isdir()):
            raise ValueError(f"a shipped pack holds files and folders inside it only, not {member.name!r}")
    return members


def relocate(value: Any, moved: dict[str, str], ws: Workspace) -> Any:
    """`value` (a job, or anything in it) with the paths `moved` names replaced, and every workspace by
    `ws`."""
    if isinstance(value, Workspace):
        return ws
    if isinstance(value, Path):
        return Path(_moved(str(value), moved))
    if isinstance(value, str):
        return _moved(value, moved)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{f.name: relocate(getattr(value, f.name), moved, ws)
                                             for f in dataclasses.fields(value) if f.init})
    if isinstance(value, (tuple, list)):
        return type(value)(relocate(v, moved, ws) for v in value)
    if isinstance(value, dict):
        return {k: relocate(v, moved, ws) for k, v in value.items()}
    return value


def _moved(text: str, moved: dict[str, str]) -> str:
    for old, new in moved.items():
        if text == old or text.startswith(old + "/"):
            return new + text[len(old):]
    return text


def named_back(error: str | None, back: dict[str, str]) -> str | None:
    """An error message naming the sender's paths, not this machine's copies of them."""
    for here, there in back.items():
        error = error and error.replace(here, there)
    return error
