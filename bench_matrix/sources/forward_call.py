"""How a factory's module takes the model's inputs. Every backend calls it with them positionally, in their
order; named after forward's parameters but not all of them in their order, they are passed on under their own
names. Inputs that cannot be matched are refused at plan time."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

POSITIONAL = ("POSITIONAL_ONLY", "POSITIONAL_OR_KEYWORD")
NAMED = ("POSITIONAL_OR_KEYWORD", "KEYWORD_ONLY")  # the parameters a keyword argument can fill
UNNAMED = ("POSITIONAL_ONLY", "VAR_POSITIONAL")  # parameters that take inputs by position, as they always did


@dataclass(frozen=True)
class Parameter:
    """A parameter of forward: its name, kind (inspect.Parameter's, by name), whether it needs a value."""

    name: str
    kind: str
    required: bool

    def describe(self) -> str:
        stars = {"VAR_POSITIONAL": "*", "VAR_KEYWORD": "**"}.get(self.kind, "")
        return f"{stars}{self.name}{'' if self.required or stars else '=…'}"


def forward_parameters(module: "torch.nn.Module") -> tuple[Parameter, ...]:
    """The parameters of the module's forward, self excluded."""
    return tuple(Parameter(p.name, p.kind.name, p.default is p.empty and not p.kind.name.startswith("VAR"))
                 for p in inspect.signature(module.forward).parameters.values())


def by_name(params: Sequence[Parameter], names: Sequence[str]) -> bool:
    """Whether forward gets the inputs by name: each is a named parameter, yet not exactly its parameters in
    order (others, e.g. a Hugging Face inputs_embeds=None, tracers would see as inputs too)."""
    named = {p.name for p in params if p.kind in NAMED}
    exactly = _in_order(params, names) and len(names) == len(params)
    return not exactly and all(name in named for name in names)


def _positional(params: Sequence[Parameter]) -> list[str]:
    return [p.name for p in params if p.kind in POSITIONAL]


def _in_order(params: Sequence[Parameter], names: Sequence[str]) -> bool:
    return list(names) == _positional(params)[:len(names)]


def call_problem(factory: str, params: Sequence[Parameter], names: Sequence[str],
                 declared: bool) -> str | None:
    """Why forward cannot take these inputs (`declared`: the matrix lists them; else they are the data's
    arrays, in the file's order), or None."""
    forward = f"forward({', '.join(p.describe() for p in params)}) of factory '{factory}'"
    what = "declared inputs" if declared else "data's arrays"
    inputs = f"the {what} ({', '.join(names)})"
    if by_name(params, names):
        return _missing(params, names, forward, inputs, declared)
    if len(names) < 2 or _in_order(params, names):
        return None
    if not declared and not any(p.kind in UNNAMED for p in params):
        return (f"{inputs} are not all named after the parameters of {forward}, and the order of a "
                f"file's arrays does not say which is which; rename the arrays after forward's parameters, "
                f"or declare the model's `inputs:` in forward's order")
    known = {p.name for p in params}
    if misplaced := [(n, p) for n, p in zip(names, _positional(params)) if n != p and n in known]:
        name, param = misplaced[0]
        return (f"{inputs} would reach {forward} by position, {name} as its parameter {param}; name every "
                f"input after one of forward's parameters (each is then passed by name), or declare them in "
                f"forward's order")
    return None


def _missing(params: Sequence[Parameter], names: Sequence[str], forward: str, inputs: str,
             declared: bool) -> str | None:
    """Why inputs passed by name leave a parameter of forward without a value, or None."""
    missing = [p.name for p in params if p.required and p.name not in names]
    if not missing:
        return None
    where = "the data and the declared inputs" if declared else "the data"
    return (f"{forward} has no default for {', '.join(missing)}, and {inputs} hold none of that name; add "
            f"{'it' if len(missing) == 1 else 'them'} to {where}")


def for_inputs(module: "torch.nn.Module", names: Sequence[str]) -> "torch.nn.Module":
    """The module taking the inputs `names` positionally: as it is, or, where by_name says so, passing each
    on to forward under its own name (keyword_forward)."""
    return keyword_forward(module, names) if by_name(forward_parameters(module), names) else module


def keyword_forward(module: "torch.nn.Module", names: Sequence[str]) -> "torch.nn.Module":
    """`module`, its class swapped for one whose forward takes `names` positionally and passes them by name;
    state_dict keys stay, and tracers (jit, FX, torch.export, ONNX) see only these (others keep defaults)."""
    base = type(module)
    code = (f"def forward(__module, {', '.join(names)}):\n"
            f"    return __forward(__module, {', '.join(f'{name}={name}' for name in names)})\n")
    namespace = {"__forward": base.forward}
    exec(code, namespace)  # names are identifiers: inspect.Parameter allows no other name
    module.__class__ = type(base.__name__, (base,), {"forward": namespace["forward"],
                                                     "__module__": base.__module__,
                                                     "__qualname__": base.__qualname__})
    return module
