"""What a real-time lap's measured figures bound, however busy the machine was (docs/closed-loop.md)."""

from __future__ import annotations


def slowest_rate(lap: dict) -> float:
    """The lowest brain rate real time allows for a lap's measured brain times: a step lasts its period plus
    at most its brain time and latency budget, however long the machine made them."""
    return 1e3 / (lap["brain_period_ms"] + lap["latency_budget_ms"] + lap["brain_ms"]["mean"])
