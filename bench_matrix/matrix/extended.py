"""The matrix schema as it is validated: the core (schema.py) with each selectable scenario's section, and
what the installed plugins declare (their targets, precisions, options and metrics)."""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from bench_matrix.matrix.requirements import with_scenarios
from bench_matrix.matrix.schema import PRECISIONS, SCHEMA
from bench_matrix.registry import scenarios

if TYPE_CHECKING:
    from bench_matrix.registry import Vocabulary


def axis_values(vocabulary: "Vocabulary") -> dict[str, list[str]]:
    """What the precision and target axes allow: the built-in precisions, then those the installed backends
    add; the targets the installed backends declare."""
    return {"precision": list(PRECISIONS) + sorted(set(vocabulary.precisions) - set(PRECISIONS)),
            "target": list(vocabulary.targets)}


def installed_schema(vocabulary: "Vocabulary", metrics: Sequence[str] = ()) -> dict[str, Any]:
    """The matrix schema extended with what the installed plugins declare: their targets and precisions on the
    axes, each backend's own options under backend_options, and the installed metric plugins."""
    schema = matrix_schema()
    properties = schema["properties"]
    axes = properties["axes"]["properties"]
    for axis, values in axis_values(vocabulary).items():
        axes[axis]["items"] = {"enum": values}
    backends = {name: {"type": "object", "additionalProperties": False, "properties": options,
                       **({} if options else {"x-message": f"backend {name} declares no options"})}
                for name, options in vocabulary.options.items()}
    backends.update({name: {"not": {}, "x-message": f"backend {name} cannot be used, so its options cannot "
                                                    f"be checked: {error}"}
                     for name, error in vocabulary.broken.items()})
    properties["backend_options"].update(properties=dict(sorted(backends.items())),
                                         additionalProperties=False)
    if metrics:
        properties["metrics"]["items"] = {"enum": list(metrics)}
    return schema


def matrix_schema() -> dict[str, Any]:
    """SCHEMA (the core) with each selectable scenario's section: the built-in matrix format."""
    schema = copy.deepcopy(SCHEMA)
    schema["properties"].update({s.name: copy.deepcopy(s.schema) for s in scenarios()})
    model = schema["properties"]["models"]["items"]["properties"]
    for holder in (schema["properties"], model):
        holder["requirements"] = with_scenarios(holder["requirements"])
    return schema


def schema_json(schema: dict[str, Any] | None = None) -> str:
    """A schema as JSON text; by default the built-in one, published in docs/matrix.schema.json."""
    return json.dumps(matrix_schema() if schema is None else schema, indent=2) + "\n"
