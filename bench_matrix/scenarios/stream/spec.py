"""The stream section's types and its fragment of the matrix schema (validated before it is read)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from bench_matrix.matrix.schema import SELECTION, seconds
from bench_matrix.matrix.spec import Selection

POLICIES = ("skip", "queue")
MAX_RATE_HZ = 10_000
MIN_FRAMES, MAX_FRAMES = 2, 1_000_000  # of round(rate_hz × duration_s)

# requirement keys under `stream`: key -> (bound, what the figure is)
REQUIREMENTS: dict[str, tuple[str, str]] = {
    "achieved_hz": ("min", "achieved stream rate, Hz"),
    "miss_share": ("max", "share of the stream's calls that ended after their deadline"),
    "drop_share": ("max", "share of the stream's frames dropped (policy skip)"),
    "jitter_p99_ms": ("max", "99th percentile of the completion jitter, ms"),
    "latency_p99_ms": ("max", "99th percentile of a call's service time in the stream, ms"),
    "e2e_p99_ms": ("max", "99th percentile of a frame's arrival-to-completion time, ms"),
}


@dataclass(frozen=True)
class StreamSpec:
    """The `stream` section: which cells serve a fixed-rate stream of frames, at what rate, for how long,
    and what happens to frames that arrive while a call still runs."""

    rate_hz: float = 30.0
    duration_s: float = 10.0
    policy: str = "skip"
    selection: Selection = Selection()

    @property
    def frames(self) -> int:
        """Frames in the stream: rate × duration, rounded."""
        return round(self.rate_hz * self.duration_s)

    def stream_dict(self) -> dict[str, Any]:
        """How the stream runs (selection aside): what a stream result depends on."""
        return {k: v for k, v in asdict(self).items() if k != "selection"}


SCHEMA: dict[str, Any] = {
    "type": "object", "additionalProperties": False,
    "description": "serve frames arriving on a fixed clock to the cells' own artifacts: achieved rate, "
                   "deadline misses, drops, jitter (docs/stream.md)",
    "properties": {
        "rate_hz": {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_RATE_HZ,
                    "description": "frames per second (default 30); a frame is due by the next's arrival"},
        "duration_s": seconds(3_600, exclusive=True, description="length of the stream (default 10 s)"),
        "policy": {"enum": list(POLICIES),
                   "description": "a frame arriving while a call runs: skip (dropped, default) or queue "
                                  "(served after it)"},
        **SELECTION,
    },
}
