"""`bench-matrix run MODEL_FILE` and `bench-matrix init MODEL_FILE`: the automatic matrix of a model file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bench_matrix.errors import UserError
from bench_matrix.workspace import Workspace, digest

if TYPE_CHECKING:
    from bench_matrix.matrix.automatic import Found, Request

MATRIX_SUFFIXES = (".yaml", ".yml")
TASKS = ("regression", "classification", "none")
MODEL_OPTIONS = {"inputs": "--input", "data": "--data", "task": "--task"}


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """--input, --data and --task: for a model file given instead of a matrix."""
    group = parser.add_argument_group("a model file instead of a matrix (an automatic matrix)")
    group.add_argument("--input", action="append", dest="inputs", metavar="NAME:SHAPE:DTYPE",
                       help="one input of the model, one sample's shape, e.g. x:3,224,224:float32 "
                            "(repeatable; for files that do not say, like TorchScript)")
    group.add_argument("--data", type=Path, help="an .npz (one array per input, labels y) or an image folder "
                                                 "(one subfolder per class); default: synthetic inputs")
    group.add_argument("--task", choices=TASKS, help="how outputs are scored against the data's labels")


def add_init(sub: argparse._SubParsersAction) -> None:
    init = sub.add_parser("init", help="print the automatic matrix of a model file, to edit and run")
    init.add_argument("model", type=Path, help="a .onnx, TorchScript .pt, torch.export .pt2, .keras or .h5 "
                                               "file, or a SavedModel folder")
    init.add_argument("-o", "--output", type=Path, help="write it to this file (default: standard output)")
    add_model_options(init)
    init.set_defaults(handler=_init)


def is_model(path: Path) -> bool:
    """Whether `run PATH` names a model (a model file, a folder) rather than a matrix; UserError: neither."""
    from bench_matrix.matrix.spec import MODEL_SUFFIXES

    suffix = path.suffix.lower()
    if suffix in MODEL_SUFFIXES or path.is_dir():
        return True
    if suffix not in MATRIX_SUFFIXES and (path.is_file() or not path.exists()):
        from bench_matrix.matrix.automatic import model_kind

        model_kind(path, _expected())  # says what was expected
    return False


def matrix_of(args: argparse.Namespace, console) -> Path:
    """The matrix `run` runs: the one given, or the automatic matrix of the model file, written in the
    workspace."""
    from bench_matrix.matrix.automatic import axes, model_name

    if not is_model(args.matrix):
        given = [option for key, option in MODEL_OPTIONS.items() if getattr(args, key) is not None]
        if given:
            raise UserError(f"{', '.join(given)}: only for a model file; {args.matrix} is a matrix, which "
                            f"declares its models' inputs and data itself")
        return args.matrix
    text, request, found = automatic(args)
    path = Workspace(args.workspace).automatic(model_name(request.path), digest(text))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    plan = " · ".join(f"{axis} {', '.join(values)}" for axis, values in axes(found).items())
    console.print(f"[bold]automatic matrix[/] of {request.path} ({request.framework}, {_data(request)}): "
                  f"{plan}; written to {path} (`bench-matrix init {args.matrix}` prints it to edit)",
                  highlight=False)
    return path


def automatic(args: argparse.Namespace) -> tuple[str, Request, Found]:
    """The automatic matrix's text, from the probe of the backends taking the model's framework."""
    from bench_matrix.matrix.automatic import EXPECTED, Request, data_path, matrix_text, model_kind
    from bench_matrix.matrix.automatic import parse_input

    path, expected = (args.model, EXPECTED) if args.command == "init" else (args.matrix, _expected())
    framework, fmt = model_kind(path, expected)
    data_path(args.data, args.task)
    request = Request(path.absolute(), framework, fmt, tuple(parse_input(t) for t in args.inputs or ()),
                      args.data and args.data.absolute(), args.task)
    found = _found(request, Workspace(args.workspace))
    return matrix_text(request, found), request, found


def _found(request: Request, ws: Workspace) -> Found:
    """Probe the installed backends on every conversion combination they declare for the model's framework."""
    from bench_matrix.executors.local import probe
    from bench_matrix.jobs import ProbeJob
    from bench_matrix.matrix.automatic import candidates, found
    from bench_matrix.registry import BackendLoadError, available, backend_class

    supports, slow = {}, {}
    entries = available()
    for name in entries:
        try:
            found_class = backend_class(name, entries)
        except BackendLoadError:
            continue  # `bench-matrix backends` says why
        supports[name] = found_class.supports
        if found_class.slow_start:
            slow[name] = found_class.slow_start
    combos = candidates(request.framework, supports, slow)
    file = (request.framework, request.format, str(request.path))
    keys = tuple((b, request.framework, s, p, t, request.format, "{}", "") for b, s, p, t in combos)
    ws.root.mkdir(parents=True, exist_ok=True)
    probed = probe(ProbeJob(ws, tuple(sorted({c[0] for c in combos})), keys, (), (file,)))
    ruled = {c: (v.invalid or v.skip) for c, v in zip(combos, (probed.rulings[k] for k in keys))}
    batches = probed.batches.get(str(request.path)) or {}
    return found(request.framework, supports, slow, ruled, probed.inputs.get(str(request.path)),
                 min(batches.values(), default=None))


def _expected() -> str:
    from bench_matrix.matrix.automatic import EXPECTED

    return f"{EXPECTED}, or a matrix .yaml"


def _data(request: Request) -> str:
    if request.data is None:
        return "synthetic inputs"
    return f"data {request.data}" + (f", task {request.task}" if request.task else "")


def _init(args: argparse.Namespace, console) -> int:
    text, _, _ = automatic(args)
    if args.output is None:
        sys.stdout.write(text)
        return 0
    try:
        args.output.write_text(text)
    except OSError as exc:
        raise UserError(f"-o {args.output}: cannot write it: {exc.strerror}") from None
    console.print(f"wrote {args.output}; next: bench-matrix plan {args.output}", highlight=False)
    return 0
