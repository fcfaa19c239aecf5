"""Settings of the single timed loop, which the interleaved rounds replaced: still read for a deprecation
period, each with one warning naming what replaced it and what its value is read as (docs/matrix.md)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bench_matrix.matrix.yamlpos import Located


@dataclass(frozen=True)
class Replaced:
    """What replaced a retired key; `setting`, if any, is read from the key's value by `convert`."""

    by: str
    setting: str | None = None
    convert: Callable[[Any], Any] = lambda value: value


REPLACED = {
    "min_iterations": Replaced("min_rounds and window_s (the rounds time calls for window_s, not a count)"),
    "min_time_s": Replaced("min_rounds and ci_target (the rounds stop once every interval is within "
                           "ci_target)"),
    "max_time_s": Replaced("timing_budget_s (the seconds of rounds a cell may take)", "timing_budget_s"),
    "ci_rel_width": Replaced("ci_target (the interval's ± half-width; ci_rel_width was its whole width)",
                             "ci_target", lambda width: width / 2),
    "throughput_time_s": Replaced("window_s (every round times a throughput window of half window_s)"),
    "passes": Replaced("the rounds and processes (every cell is timed in every round, in `processes` "
                       "processes)"),
}


def current(given: dict[str, Any], report: Located) -> dict[str, Any]:
    """The settings `given` with each retired key dropped or read as its successor (one the matrix sets
    itself wins), each warned of once."""
    settings = {key: value for key, value in given.items() if key not in REPLACED}
    for key in [key for key in given if key in REPLACED]:
        replaced = REPLACED[key]
        if replaced.setting is None:
            reading = "its value is ignored; remove it"
        elif replaced.setting in given:
            reading = f"ignored, as the matrix sets {replaced.setting}; remove it"
        else:
            settings[replaced.setting] = replaced.convert(given[key])
            reading = f"read as {replaced.setting}: {settings[replaced.setting]:g}; write that instead"
        report.warn(("settings", key), f"retired with the single timed loop, replaced by {replaced.by}; "
                                       f"{reading} (docs/matrix.md, Retired keys)")
    return settings
