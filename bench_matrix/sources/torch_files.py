"""What a PyTorch model archive may hold before torch reads it: nothing that unpickles Python objects, no
compiled code, no expression torch would evaluate, no operator that reads or writes files."""

from __future__ import annotations

import ast
import io
import json
import re
import tokenize
from typing import Any

from bench_matrix.sources import ModelFileError

# Operators that write or read files (ATen's save and from_file, the debug tensor loader): a graph calling one
# could overwrite any file the user may write. Refused in TorchScript code and torch.export graphs alike.
FILE_OPS = frozenset({"save", "from_file", "load_tensor"})
# torch's own operator namespaces; an operator of another library's namespace is refused.
TORCH_NAMESPACES = frozenset({"aten", "prim", "prims", "quantized", "_quantized", "quantized_decomposed",
                              "mkldnn", "mkldnn_prepacked", "onednn", "prepacked", "sparse", "mkl",
                              "rngprims", "higher_order", "_native"})
# What a torch.export shape expression (sympy's srepr, read back with sympify, i.e. Python's eval) may hold:
# sympy's and torch's arithmetic, comparison and logic classes, symbols (s0, u1), and plain literals.
SYMPY_NAMES = frozenset({
    "Add", "Mul", "Pow", "Mod", "Max", "Min", "Abs", "floor", "ceiling", "Piecewise", "ExprCondPair",
    "Symbol", "Integer", "Rational", "Float", "Zero", "One", "NegativeOne", "Half", "NaN", "Infinity",
    "NegativeInfinity", "IntInfinity", "NegativeIntInfinity", "Equality", "Unequality", "StrictLessThan",
    "LessThan", "StrictGreaterThan", "GreaterThan", "Eq", "Ne", "Lt", "Le", "Gt", "Ge", "And", "Or", "Not",
    "BooleanTrue", "BooleanFalse", "true", "false", "oo", "zoo", "nan", "int_oo",
    "FloorDiv", "ModularIndexing", "Where", "PythonMod", "CleanDiv", "CeilToInt", "FloorToInt", "CeilDiv",
    "LShift", "RShift", "PowByNatural", "FloatPow", "FloatTrueDiv", "IntTrueDiv",
    "IsNonOverlappingAndDenseIndicator", "TruncToFloat", "TruncToInt", "RoundToInt", "RoundDecimal",
    "ToFloat", "Identity"})
LITERAL_CALLS = frozenset({"Symbol", "Integer", "Rational", "Float"})  # a string argument: a name or number
PLAIN_STRING = re.compile(r"[\w.+\-/ ]{1,100}\Z")
SYMBOL = re.compile(r"[a-z]+\d+\Z")
EXPRESSION_NODES = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.BoolOp, ast.Compare, ast.Call, ast.keyword,
                    ast.Tuple, ast.Name, ast.Constant, ast.Load, ast.operator, ast.unaryop, ast.boolop,
                    ast.cmpop)
RE_SCRIPT = "save the model with torch.jit.save(torch.jit.script(module), path)"
RE_EXPORT = "re-export the model with torch.export.export and save it with torch.export.save"


def brief(exc: BaseException) -> str:
    """'Type: first line' of a library's exception, without torch's advice on loading unsafely."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    text = text.split(". This is an internal miniz error")[0]
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__


def check_export_archive(data: bytes, label: str) -> None:
    """ModelFileError unless torch's .pt2 loader can read this archive without running code from it."""
    import torch

    try:
        reader = torch._C.PyTorchFileReader(io.BytesIO(data))  # the reader torch.export.load itself uses
        records = set(reader.get_all_records())
    except Exception as exc:  # RuntimeError from the zip reader, ValueError from a short file
        raise ModelFileError(f"{label}: is not a torch.export archive (.pt2): {brief(exc)}; "
                             f"{RE_EXPORT}") from None
    if "archive_format" not in records or reader.get_record("archive_format") != b"pt2":
        raise ModelFileError(f"{label}: is not a torch.export archive of the current format (it has no "
                             f"archive_format 'pt2' entry: written by an older torch, or not by "
                             f"torch.export.save); {RE_EXPORT} of torch {torch.__version__}")
    problem = ("it holds AOTInductor-compiled code (shared libraries)"
               if any(r.startswith("data/aotinductor/") for r in records) else None)
    models = sorted(r[len("models/"):-len(".json")] for r in records if r.startswith("models/"))
    if not models:
        raise ModelFileError(f"{label}: holds no exported program (no models/*.json entry); {RE_EXPORT}")
    for name in models:
        problem = problem or _program_problem(reader, records, name)
    if problem:
        raise refuse(label, problem, f"{RE_EXPORT} of torch {torch.__version__} from a plain nn.Module whose "
                                     f"weights and constants are tensors")


def _program_problem(reader: Any, records: set[str], name: str) -> str | None:
    """What in exported program `name` torch would unpickle, or evaluate, unsafely; None when nothing."""
    for kind in ("weights", "constants"):
        if f"data/{kind}/{name}.pt" in records:
            return f"it stores its {kind} as a pickle (data/{kind}/{name}.pt, an older format)"
        record = f"data/{kind}/{name}_{kind}_config.json"
        config = _json(reader, record) if record in records else {"config": {}}
        entries = config.get("config") if isinstance(config, dict) else None
        if not isinstance(entries, dict) or not all(isinstance(m, dict) for m in entries.values()):
            return f"its entry {record} is not a payload configuration torch.export.save writes"
        for fqn, meta in entries.items():
            plain = str(meta.get("path_name", "")).startswith(("weight_", "tensor_"))
            if meta.get("use_pickle") or not plain:
                return f"it stores {kind[:-1]} '{fqn}' as a pickled object, not as a plain tensor ({record})"
    if problem := _sample_inputs_problem(reader, records, f"data/sample_inputs/{name}.pt"):
        return problem
    program = _json(reader, f"models/{name}.json")
    return _graph_problem(program, f"models/{name}.json") if program is not None else (
        f"its entry models/{name}.json is not valid JSON")


def _json(reader: Any, record: str) -> Any:
    """A JSON record of the archive, or None when it is not JSON."""
    try:
        return json.loads(reader.get_record(record))
    except (RuntimeError, ValueError, RecursionError):
        return None


def _sample_inputs_problem(reader: Any, records: set[str], record: str) -> str | None:
    """torch unpickles the sample inputs without weights_only when weights_only fails: refuse them unless
    weights_only reads them, called as torch calls it (it then succeeds for torch too, on the same bytes)."""
    import pickle

    import torch

    data = reader.get_record(record) if record in records else b""
    if not data:
        return None
    try:
        torch.load(io.BytesIO(data), weights_only=True)
    except pickle.UnpicklingError as exc:
        return (f"its sample inputs ({record}) hold pickled objects other than tensors "
                f"({unpickling_cause(exc)})")
    except Exception as exc:  # torch would unpickle them without weights_only after any failure
        return (f"its sample inputs ({record}) are not a file torch.load reads with weights_only "
                f"({brief(exc)})")
    return None


def unpickling_cause(exc: BaseException) -> str:
    """The Python object torch's weights-only unpickler refused, from its message."""
    found = re.search(r"GLOBAL ([\w.]+)", str(exc))
    return f"it refers to {found.group(1)}" if found else brief(exc).split("\n")[0]


def _graph_problem(tree: Any, record: str) -> str | None:
    """The first operator that touches files or is not torch's, or shape expression that is not plain
    arithmetic (torch evaluates those with sympy, i.e. Python's eval), anywhere in the program's JSON."""
    stack = [tree]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            stack.extend(item)
        elif isinstance(item, dict):
            target, expression = item.get("target"), item.get("expr_str")
            if isinstance(target, str) and "inputs" in item and (problem := operator_problem(target)):
                return f"its graph ({record}) calls {problem}"
            if expression is not None and not safe_expression(expression):
                return (f"its graph ({record}) holds shape expression {str(expression)[:80]!r}, which is not "
                        f"plain arithmetic on symbols (torch evaluates these with Python's eval)")
            stack.extend(item.values())
    return None


def operator_problem(target: str) -> str | None:
    """Why a graph may not call operator `target` ('torch.ops.aten.add.Tensor'), or None."""
    if not target.startswith("torch.ops."):
        return None  # torch's verifier admits only operators, a few builtins and torch.sym_* functions
    namespace, _, rest = target[len("torch.ops."):].partition(".")
    if namespace not in TORCH_NAMESPACES:
        return f"operator {target}, which is not one of torch's own (namespace '{namespace}')"
    if rest.partition(".")[0] in FILE_OPS:
        return f"operator {target}, which reads or writes files"
    return None


def safe_expression(text: Any) -> bool:
    """Whether a sympy expression string is arithmetic, comparisons and known sympy classes on symbols and
    literals only (a string only as the name or number a Symbol, Integer, Rational or Float is made from)."""
    if not isinstance(text, str) or len(text) > 10_000:
        return False
    try:
        tree = ast.parse(text, mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return False
    literals = {id(arg) for node in ast.walk(tree) if isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name) and node.func.id in LITERAL_CALLS for arg in node.args}
    return all(_safe_node(node, literals) for node in ast.walk(tree))


def _safe_node(node: ast.AST, literals: set[int]) -> bool:
    if not isinstance(node, EXPRESSION_NODES):
        return False
    if isinstance(node, ast.Name):
        return bool(SYMBOL.match(node.id)) or node.id in SYMPY_NAMES
    if isinstance(node, ast.Constant):
        if isinstance(node.value, str):
            return id(node) in literals and bool(PLAIN_STRING.match(node.value))
        return type(node.value) in (int, float, bool)
    if isinstance(node, ast.Call):
        literal = isinstance(node.func, ast.Name) and node.func.id in LITERAL_CALLS
        return isinstance(node.func, ast.Name) and all(
            literal and isinstance(k.value, ast.Constant) and type(k.value.value) in (bool, int)
            for k in node.keywords)
    return True


def check_torchscript(data: bytes, label: str) -> None:
    """ModelFileError unless this TorchScript archive's code calls only torch's own file-free operators: it
    runs on load (__setstate__) and each call, and may call any operator (ATen's save writes any file)."""
    import torch

    try:
        reader = torch._C.PyTorchFileReader(io.BytesIO(data))  # the reader torch.jit.load itself uses
        records = reader.get_all_records()
    except Exception as exc:  # RuntimeError from the zip reader, ValueError from a short file
        raise ModelFileError(f"{label}: is not a TorchScript archive: {brief(exc)}; {RE_SCRIPT}") from None
    code = [r for r in records if r.startswith("code/") and r.endswith(".py")]
    if not code or "constants.pkl" not in records:
        what = ("a torch.save file (a state_dict? give it as factory + weights instead of file)"
                if "data.pkl" in records else "a zip archive that is not one")
        raise ModelFileError(f"{label}: is not a TorchScript archive (it has no code/ and constants.pkl "
                             f"entries): it is {what}; {RE_SCRIPT}")
    for record in code:
        if problem := _code_problem(reader.get_record(record).decode("utf-8", "replace")):
            raise refuse(label, f"its TorchScript code ({record}) {problem}",
                         f"{RE_SCRIPT} from a module that calls no such operator")


def _code_problem(source: str) -> str | None:
    """The first file operator or foreign operator namespace TorchScript source refers to, or None."""
    try:
        tokens = [t for t in tokenize.generate_tokens(io.StringIO(source).readline)
                  if t.type in (tokenize.NAME, tokenize.STRING, tokenize.OP)]
    except (tokenize.TokenError, SyntaxError) as exc:
        return f"is not valid TorchScript source ({brief(exc)})"
    for i, token in enumerate(tokens):
        word = _literal(token.string) if token.type == tokenize.STRING else token.string
        if word in FILE_OPS:
            return f"calls operator '{word}', which reads or writes files"
        if token.string == "ops" and i + 2 < len(tokens) and tokens[i + 1].string == ".":
            if (namespace := tokens[i + 2].string) not in TORCH_NAMESPACES:
                return f"calls operators of namespace '{namespace}', which is not one of torch's own"
    return None


def _literal(text: str) -> str:
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return ""
    return value if isinstance(value, str) else ""


def refuse(label: str, problem: str, what_to_do: str) -> ModelFileError:
    """The error for a model file bench-matrix will not load, because of what it holds."""
    return ModelFileError(f"{label}: {problem}; bench-matrix refuses it, since loading or running it could "
                          f"run code or touch files as the file dictates: {what_to_do}")
