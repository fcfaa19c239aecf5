"""Validation of matrix data against its JSON Schema: a validator whose integers and numbers are what YAML
users mean, and each error described at its file line, with what is allowed."""

from __future__ import annotations

import math
import re
from typing import Any

import jsonschema

from bench_matrix.matrix.yamlpos import Located, suggest


def _is_integer(_checker: Any, value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # 2.0 and True are not counts


def _is_number(_checker: Any, value: Any) -> bool:
    return _is_integer(_checker, value) or (isinstance(value, float) and math.isfinite(value))


StrictValidator = jsonschema.validators.extend(
    jsonschema.Draft202012Validator,
    type_checker=jsonschema.Draft202012Validator.TYPE_CHECKER.redefine_many(
        {"integer": _is_integer, "number": _is_number}))


def describe(error: jsonschema.ValidationError, report: Located) -> None:
    at = tuple(error.absolute_path)
    schema, value, kind = error.schema, error.instance, error.validator
    if kind == "additionalProperties" and isinstance(value, dict):
        known = schema.get("properties", {})
        allowed = sorted(k for k, rule in known.items() if not rule.get("deprecated"))
        patterns = list(schema.get("patternProperties", {}))
        for key in [k for k in value if k not in known and not any(re.search(p, k) for p in patterns)]:
            none = schema.get("x-message", "no keys are allowed here")
            hint = f"allowed: {', '.join(allowed)}" if allowed else none
            report.add(at + (key,), f"unknown key '{key}'; {hint}{suggest(key, allowed)}")
    elif kind in ("enum", "const"):
        allowed = schema.get("enum", [schema.get("const")])
        report.add(at, f"'{value}' is not allowed; allowed: {', '.join(map(str, allowed))}{suggest(value, allowed)}")
    elif kind == "required":
        report.add(at, f"missing required key {error.message.split(' is a required')[0]}")
    elif kind == "type":
        report.add(at, _type_message(error.validator_value, value))
    elif kind == "oneOf" and (unknown := _hidden_unknown_keys(schema, value)):
        for key in unknown:
            allowed = ", ".join(sorted(schema["properties"]))
            report.add(at + (key,), f"unknown key '{key}'; allowed: {allowed} (and the options of the kind)"
                                    f"{suggest(key, sorted(_known_keys(schema)))}")
    elif kind in ("oneOf", "pattern", "not") and "x-message" in schema:
        report.add(at, schema["x-message"] + (f" (got {value!r})" if kind == "pattern" else ""))
    elif kind in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        sign = {"minimum": ">=", "exclusiveMinimum": ">", "maximum": "<=", "exclusiveMaximum": "<"}[kind]
        report.add(at, f"must be {sign} {error.validator_value}, got {value!r}")
    elif kind in ("minItems", "maxItems", "minProperties"):
        report.add(at, error.message.replace("[]", "the list").replace("{}", "the mapping"))
    elif kind == "uniqueItems":
        report.add(at, f"lists a value twice: {value!r}")
    else:
        report.add(at, error.message)


def _type_message(expected: str | list[str], value: Any) -> str:
    names = expected if isinstance(expected, str) else " or ".join(expected)
    got = f"got {type(value).__name__} {value!r}"
    if isinstance(value, float) and not math.isfinite(value):
        return f"expected a finite {names}, {got} (.nan and .inf are not allowed)"
    if isinstance(value, float) and value.is_integer() and "integer" in expected:
        return f"expected {names}, {got}; write it without a decimal point"
    return f"expected {names}, {got}"


def _known_keys(schema: dict[str, Any]) -> set[str]:
    """Keys an object schema allows in any of its conditional branches (allOf: if/then)."""
    branches = [b.get("then", {}).get("properties", {}) for b in schema.get("allOf", [])]
    return set(schema.get("properties", {})).union(*branches)


def _hidden_unknown_keys(schema: dict[str, Any], value: Any) -> list[str]:
    """Unknown keys no other error reports: an object schema, without additionalProperties, failed oneOf."""
    if not isinstance(value, dict) or "additionalProperties" in schema or "properties" not in schema:
        return []
    known = _known_keys(schema)
    return [key for key in value if key not in known]
