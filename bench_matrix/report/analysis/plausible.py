"""Ok records that cannot be right, from their stored figures alone (docs/results.md §8): an artifact smaller
than its parameters fit in at its precision, an int8 cell whose outputs are bit-identical to an fp32 cell's,
an fp32 cell farther from the baseline than float noise goes."""

from __future__ import annotations

from collections.abc import Sequence

from bench_matrix.store import CellRecord

# Bytes a parameter takes at each precision; an artifact under half of its parameters' bytes is not all
# there (folding a BatchNorm into its convolution, the most a converter drops, removes a small share).
PARAM_BYTES = {"fp32": 4, "fp16": 2, "bf16": 2, "int8": 1}
SIZE_SHARE = 0.5
# An fp32 cell converted as it is (strategy none) computes what the baseline does up to summation order: on
# the conformance kit's models the CPU backends' fp32 outputs are 127-137 dB from the framework's (or
# identical), fp16 65-68 dB, bf16 48-50, int8 30-36. A GPU's fp32 may multiply in TF32 (cuDNN's default for
# PyTorch's convolutions), with fp16's 10-bit mantissa, so it can come near fp16: below this, the fp32
# outputs are not the model's (an error RMS over 0.1 % of the outputs' RMS).
FP32_SNR_DB = 60.0


def implausible(records: Sequence[CellRecord]) -> dict[str, str]:
    """Why each ok record of one model cannot be right, by cell key (records that can are absent)."""
    fp32 = {r.metrics.task.outputs_sha256: r for r in records if r.cell.precision == "fp32"}
    found = {}
    for record in records:
        reasons = [reason for reason in (_size(record), _identical(record, fp32), _far(record)) if reason]
        if reasons:
            found[record.cell.key] = "; ".join(reasons)
    return found


def _size(record: CellRecord) -> str | None:
    size, per = record.metrics.size, PARAM_BYTES.get(record.cell.precision)
    if not (isinstance(size.bytes, int) and isinstance(size.params, int) and per):
        return None
    needed = size.params * per
    if size.bytes >= SIZE_SHARE * needed:
        return None
    return (f"its artifact is {size.bytes:,} bytes, but its {size.params:,} parameters take {needed:,} at "
            f"{record.cell.precision}: the artifact is not all in its directory")


def _identical(record: CellRecord, fp32: dict[str | None, CellRecord]) -> str | None:
    """int8 rounds every quantised tensor to 256 levels: outputs bit-identical to an fp32 cell's are an fp32
    program (fp16 and bf16 can leave a tiny model's bits alone: summary.suspects notes those)."""
    digest = record.metrics.task.outputs_sha256
    same = fp32.get(digest) if isinstance(digest, str) and record.cell.precision == "int8" else None
    if same is None:
        return None
    return (f"its outputs are bit-identical to {same.cell.label}'s: {record.cell.precision} was not applied")


def _far(record: CellRecord) -> str | None:
    snr = record.metrics.task.snr_db
    if record.cell.precision != "fp32" or record.cell.strategy != "none" or not isinstance(snr, int | float):
        return None
    if snr >= FP32_SNR_DB:
        return None
    return (f"its fp32 outputs are at {snr:.1f} dB SNR to the baseline's, where float noise stays above "
            f"{FP32_SNR_DB:g} dB")
