"""What changes on ARM: each cell of matrices/arm64-emulated.yaml measured here (x86) and on the emulated
arm64 board, side by side, from the two stores (nothing is re-measured). The same artifact and the same test
split on both sides, so a difference is the architecture's: its kernels and their rounding. Timings are left out
(the board's are qemu's). Prints a Markdown page.

    .venv/bin/python benchmarks/arm64_vs_x86.py .bench-matrix/arm64/x86.sqlite \
        .bench-matrix/arm64/arm64.sqlite > reports/arm64-emulated/vs-x86.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench_matrix.report.analysis.summary import metric
from bench_matrix.store import CellRecord, ResultStore

SHORT = 110  # characters of a reason shown
NOISE = 1e-5  # a relative MSE change below this is float rounding (fp32 sums of the samples in another order)


def _latest(path: Path) -> dict[str, CellRecord]:
    """The newest record of each cell in a store."""
    found: dict[str, CellRecord] = {}
    for record in ResultStore(path).records():
        found[record.cell.key] = record
    return found


def _figure(record: CellRecord | None, key: str) -> float | None:
    return metric(record, key) if record is not None and record.status == "ok" else None


def _number(value: float | None) -> str:
    return "—" if value is None else f"{value:.6g}"


def _status(record: CellRecord | None) -> str:
    if record is None:
        return "not run"
    if record.status == "ok":
        return "ok"
    reason = (record.reason or "").splitlines()[0]
    return f"{record.status}: {reason[:SHORT]}" + ("…" if len(reason) > SHORT else "")


def _verdict(x86: float | None, arm: float | None) -> str:
    if x86 is None or arm is None:
        return "—"
    change = (arm - x86) / x86 if x86 else 0.0
    if abs(change) <= NOISE:
        return "same (float noise)"
    return f"**differs: {change:+.3%}**"


def _row(key: str, x86: CellRecord | None, arm: CellRecord | None) -> str:
    mse = (_figure(x86, "mse"), _figure(arm, "mse"))
    diff = (_figure(x86, "max_abs_diff_vs_baseline"), _figure(arm, "max_abs_diff_vs_baseline"))
    status = _status(arm) if _status(x86) == "ok" else f"x86 {_status(x86)}; arm64 {_status(arm)}"
    return (f"| {key} | {status} | {_number(mse[0])} | {_number(mse[1])} | {_verdict(*mse)} | "
            f"{_number(diff[0])} | {_number(diff[1])} |")


def page(x86: dict[str, CellRecord], arm: dict[str, CellRecord]) -> str:
    keys = sorted(set(x86) | set(arm))
    ok = [k for k in keys if _status(x86.get(k)) == _status(arm.get(k)) == "ok"]
    differ = [k for k in ok if _verdict(_figure(x86[k], "mse"), _figure(arm[k], "mse")).startswith("**")]
    scored = sorted({int(n) for k in ok for side in (x86, arm) if (n := _figure(side[k], "test_samples"))})
    lines = ["# What changes on ARM: x86 and the emulated arm64 board, cell by cell", "",
             f"{len(ok)} cells ok on both; {len(differ)} of them with a test MSE that differs beyond float "
             f"noise (relative {NOISE:g}): {', '.join(differ) or 'none'}. Same artifact, same test split "
             f"({' or '.join(map(str, scored)) or 'no'} samples scored); max |Δ| is each side's largest "
             "difference from the fp32 reference outputs "
             "computed on x86. Timings are not compared: the board's are qemu's.", "",
             "| cell | on arm64 | MSE x86 | MSE arm64 | arm64 vs x86 | max \\|Δ\\| x86 | max \\|Δ\\| arm64 |",
             "|---|---|---|---|---|---|---|"]
    return "\n".join(lines + [_row(key, x86.get(key), arm.get(key)) for key in keys]) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("x86", type=Path)
    parser.add_argument("arm64", type=Path)
    args = parser.parse_args()
    print(page(_latest(args.x86), _latest(args.arm64)), end="")


if __name__ == "__main__":
    main()
