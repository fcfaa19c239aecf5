"""Named model inputs: their declared shape and dtype, a batch of them, and binding data arrays to them; a
model's outputs as one flat list."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

# A batch of model inputs: one array per named input, batch axis first, in the model's input order.
Inputs = dict[str, np.ndarray]
DTYPES = ("float32", "float16", "float64", "bfloat16", "int64", "int32", "int16", "int8", "uint8", "bool")
SINGLE = "x"  # the name of the one input array of a single-input dataset
OPEN_LENGTH = 8  # the length synthetic data gives an open axis (None) of an input
# Casts from a data array's dtype to the model input's dtype that cannot change a value that matters.
SAFE_CASTS = {("float64", "float32"), ("float16", "float32"), ("uint8", "float32"), ("int32", "int64"),
              ("int64", "int32"), ("int16", "int64"), ("int16", "int32"), ("uint8", "int64"),
              ("uint8", "int32"), ("bool", "int64"), ("bool", "int32"), ("int8", "int64"),
              ("int8", "int32"), ("bool", "float32"),
              ("float32", "bfloat16"), ("float32", "float16")}


@dataclass(frozen=True)
class TensorSpec:
    """One model input: its name, the shape of one sample (no batch axis; None = any length), its dtype and,
    for synthetic data, the range its values are drawn from ([low, high) for integers)."""

    name: str
    shape: tuple[int | None, ...]
    dtype: str = "float32"
    range: tuple[float, float] | None = None

    @property
    def is_integer(self) -> bool:
        return self.dtype.startswith(("int", "uint")) or self.dtype == "bool"

    def describe(self) -> str:
        dims = ", ".join("?" if d is None else str(d) for d in self.shape)
        return f"{self.name} ({dims}) {self.dtype}"

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "shape": list(self.shape), "dtype": self.dtype,
                "range": None if self.range is None else list(self.range)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "TensorSpec":
        value_range = data.get("range")
        return cls(name=data["name"], shape=tuple(data["shape"]), dtype=data.get("dtype", "float32"),
                   range=None if value_range is None else (value_range[0], value_range[1]))


def specs_to_list(specs: Sequence[TensorSpec]) -> list[dict[str, Any]]:
    return [s.to_dict() for s in specs]


def specs_from_list(data: Sequence[Mapping[str, Any]]) -> tuple[TensorSpec, ...]:
    return tuple(TensorSpec.from_dict(d) for d in data)


def concrete(shape: Sequence[int | None], length: int = OPEN_LENGTH) -> tuple[int, ...]:
    """A concrete sample shape: every free axis (None) given `length`."""
    return tuple(length if d is None else int(d) for d in shape)


def open_axes(spec: TensorSpec) -> tuple[int, ...]:
    """The input's open axes (None), numbered as in a batch: the batch axis is 0."""
    return tuple(axis for axis, d in enumerate(spec.shape, start=1) if d is None)


def axes_text(axes: Sequence[int]) -> str:
    """Axis numbers in words: 'axis 2', 'axes 2 and 3'."""
    numbers = [str(axis) for axis in axes]
    return f"axis {numbers[0]}" if len(numbers) == 1 else f"axes {', '.join(numbers[:-1])} and {numbers[-1]}"


def shape_text(shape: Sequence[int | None]) -> str:
    """A sample shape as '3×224×224' (? for an open axis; 'scalar' for none)."""
    return "×".join("?" if d is None else str(d) for d in shape) or "scalar"


def fed(data: Mapping[str, TensorSpec], model: Sequence[TensorSpec]) -> tuple[TensorSpec, ...]:
    """The model's inputs with the per-sample shape of the data array feeding each (a single array feeds a
    single input); the data's arrays themselves where the model's inputs are not known."""
    if not model:
        return tuple(data.values())
    names = data_names(data, model)
    return tuple(replace(spec, shape=data[name].shape) for spec, name in zip(model, names) if name in data)


def random_inputs(specs: Sequence[TensorSpec], batch: int, seed: int) -> Inputs:
    """Random inputs of the declared shapes and dtypes: floats from N(0, 1) (or uniform in `range`),
    integers uniform in [low, high) of `range` (default [0, 2): valid token ids and masks of any model)."""
    rng = np.random.default_rng(seed)
    out: Inputs = {}
    for spec in specs:
        shape = (batch, *concrete(spec.shape))
        if spec.is_integer:
            low, high = spec.range or (0, 2)
            values = rng.integers(int(low), int(high), size=shape)
            out[spec.name] = values.astype(np.bool_ if spec.dtype == "bool" else spec.dtype)
        else:
            values = rng.uniform(*spec.range, size=shape) if spec.range else rng.standard_normal(shape)
            out[spec.name] = values.astype(np.float32 if spec.dtype == "bfloat16" else spec.dtype)
    return out


def example_inputs(specs: Sequence[TensorSpec], batch: int = 2, seed: int = 0) -> Inputs:
    """Inputs to trace or export a model with: floats uniform in [0, 1), integers all ones (a valid token id
    and an 'attend' mask for any model)."""
    rng = np.random.default_rng(seed)
    out: Inputs = {}
    for spec in specs:
        shape = (batch, *concrete(spec.shape))
        if spec.is_integer:
            out[spec.name] = np.ones(shape, np.bool_ if spec.dtype == "bool" else spec.dtype)
        else:
            out[spec.name] = rng.random(shape, dtype=np.float32)
    return out


def take(inputs: Mapping[str, np.ndarray], index: Any) -> Inputs:
    """The same rows (a slice or an index array) of every input."""
    return {name: array[index] for name, array in inputs.items()}


def count(inputs: Mapping[str, np.ndarray]) -> int:
    """The batch size of a batch of inputs."""
    return len(next(iter(inputs.values())))


def resize(inputs: Mapping[str, np.ndarray], n: int) -> Inputs:
    """A batch of exactly n samples: the first samples repeated (or cut) to fill it."""
    return {name: np.resize(a, (n, *a.shape[1:])) for name, a in inputs.items()}


def binding_problem(data: Mapping[str, TensorSpec], model: Sequence[TensorSpec]) -> str | None:
    """Why the data's arrays cannot feed the model's inputs (a missing input, another shape or dtype), or
    None; a single data array named `x` feeds a single-input model whatever the input's name."""
    names = data_names(data, model)
    for spec, name in zip(model, names):
        if name not in data:
            provided = ", ".join(data) or "nothing"
            return f"the model's input {spec.describe()} is not in the data (it provides {provided})"
        given = data[name]
        if not shape_fits(given.shape, spec.shape):
            return (f"the model's input {spec.describe()} gets the data's '{name}' of shape "
                    f"({', '.join(map(str, given.shape))}) per sample")
        if given.dtype != spec.dtype and (given.dtype, spec.dtype) not in SAFE_CASTS:
            return (f"the model's input {spec.describe()} does not take the data's '{name}' of dtype "
                    f"{given.dtype}: convert the data or declare the input's dtype")
    return None


def bind(data: Mapping[str, np.ndarray], model: Sequence[TensorSpec]) -> Inputs:
    """The data's arrays as the model's inputs: renamed (a single `x`), in the model's order and dtypes."""
    specs = {name: TensorSpec(name, a.shape[1:], str(a.dtype)) for name, a in data.items()}
    names = data_names(specs, model)
    out: Inputs = {}
    for spec, name in zip(model, names):
        array = data[name]
        dtype = np.float32 if spec.dtype == "bfloat16" else np.dtype(spec.dtype)
        out[spec.name] = np.ascontiguousarray(array, dtype=dtype)
    return out


def shape_fits(given: Sequence[int | None], model: Sequence[int | None]) -> bool:
    """Whether a per-sample shape fits the model's: as many axes, equal wherever both are known."""
    return len(given) == len(model) and all(m is None or g is None or m == g for m, g in zip(model, given))


def data_names(data: Mapping[str, Any], model: Sequence[TensorSpec]) -> list[str]:
    """The data array feeding each model input, in the model's order (a single array feeds a single input)."""
    if len(model) == 1 and model[0].name not in data and len(data) == 1:
        return [next(iter(data))]
    return [spec.name for spec in model]


def flat_outputs(outputs: Any) -> list[Any]:
    """A model's outputs as a flat list: a tensor alone; a tuple or list in order; a dict (a Keras model with
    named outputs, a Hugging Face ModelOutput) by sorted key; nested structures depth first; None dropped."""
    if outputs is None:
        return []
    if isinstance(outputs, Mapping):
        return [leaf for key in sorted(outputs) for leaf in flat_outputs(outputs[key])]
    if isinstance(outputs, (list, tuple)):
        return [leaf for item in outputs for leaf in flat_outputs(item)]
    return [outputs]
