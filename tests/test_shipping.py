"""What travels to a device unpacks there on every Python bench-matrix supports, Debian bookworm's 3.11.2
(a Raspberry Pi's) included, whose tarfile has no extraction filters; a pack reaching outside is refused."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path

import pytest

from bench_matrix.executors.shipping import extract, pack
from bench_matrix.workspace import Workspace


@pytest.fixture
def old_tarfile(monkeypatch: pytest.MonkeyPatch) -> None:
    """tarfile as Python 3.11.0 to 3.11.3 have it: no data_filter, and extractall takes no `filter`."""
    monkeypatch.delattr(tarfile, "data_filter")
    extractall = tarfile.TarFile.extractall

    def without_filter(self, path=".", members=None, *, numeric_owner=False, **rest):
        if rest:
            raise TypeError(f"TarFile.extractall() got an unexpected keyword argument {next(iter(rest))!r}")
        return extractall(self, path, members, numeric_owner=numeric_owner)

    monkeypatch.setattr(tarfile.TarFile, "extractall", without_filter)


def _folder(root: Path) -> Path:
    (root / "model" / "weights").mkdir(parents=True)
    (root / "model" / "model.onnx").write_bytes(b"onnx")
    (root / "model" / "weights" / "w.bin").write_bytes(b"\0" * 64)
    return root / "model"


def test_a_pack_unpacks_where_tarfile_has_no_extraction_filters(tmp_path: Path, old_tarfile) -> None:
    _, data = pack(_folder(tmp_path / "here"))
    extract(data, tmp_path / "there" / "key", Workspace(tmp_path / "ws"))
    assert (tmp_path / "there" / "key" / "model" / "weights" / "w.bin").read_bytes() == b"\0" * 64


@pytest.mark.parametrize("name", ["../escaped", "/etc/escaped", "link"])
def test_a_pack_reaching_outside_its_folder_is_refused_there_too(tmp_path: Path, old_tarfile, name) -> None:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        info = tarfile.TarInfo(name)
        if name == "link":
            info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tar.addfile(info, io.BytesIO(b""))
    with pytest.raises(ValueError, match="files and folders inside it only"):
        extract(buffer.getvalue(), tmp_path / "there" / "key", Workspace(tmp_path / "ws"))
    assert not (tmp_path / "escaped").exists() and not (tmp_path / "there" / "key").exists()
