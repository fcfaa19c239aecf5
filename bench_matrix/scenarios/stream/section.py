"""The matrix's `stream` section, read after schema validation: its frame count bounded, its selectors checked
against the matrix."""

from __future__ import annotations

from typing import Any

from bench_matrix.matrix.load import Loading
from bench_matrix.scenarios.stream.spec import MAX_FRAMES, MIN_FRAMES, StreamSpec

AT = ("stream",)


def stream(data: dict[str, Any], loading: Loading) -> StreamSpec:
    """The typed section; every problem is added to `loading.report`."""
    report = loading.report
    spec = StreamSpec(rate_hz=data.get("rate_hz", StreamSpec.rate_hz),
                      duration_s=data.get("duration_s", StreamSpec.duration_s),
                      policy=data.get("policy", StreamSpec.policy), selection=loading.selection(AT, data))
    if not MIN_FRAMES <= spec.frames <= MAX_FRAMES:
        report.add(AT + ("duration_s",), f"rate_hz × duration_s makes {spec.frames} frames "
                                         f"({spec.rate_hz:g} Hz × {spec.duration_s:g} s); allowed: "
                                         f"{MIN_FRAMES} to {MAX_FRAMES:,}")
    return spec
