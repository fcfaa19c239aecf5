"""int8 for the openvino backend: NNCF's post-training quantisation of the fp32 OpenVINO model, calibrated on
the calibration split, with activation ranges that cover every calibration sample."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import ConvertRequest, count, installed_versions

from ._common import CALIBRATION_BATCH, batches, calibration_data
from ._openvino import DEVICES, openvino

if TYPE_CHECKING:
    import openvino as ov

# Activation ranges per `method`. NNCF's default, MEAN_MINMAX, averages each calibration item's min and max:
# fed one sample per item, as NNCF's examples do, it clips every activation beyond an average sample, which
# tripled PilotNet's int8 error. minmax takes the extremes over all samples (NNCF's MINMAX, whatever the
# batching); percentile is NNCF's MEAN_QUANTILE: each item's 1e-4 and 1 - 1e-4 quantiles, averaged.
RANGES = {"minmax": "MINMAX", "percentile": "MEAN_QUANTILE"}
METHODS = tuple(RANGES)
ITEM = CALIBRATION_BATCH  # samples per NNCF data item (the last may be smaller)
PRESET = "MIXED"  # symmetric weights, asymmetric activations (NNCF's default for CNNs: symmetric both)
FAST_BIAS_CORRECTION = True
# 7-bit weights in every layer on the CPU: without VNNI, x86 int8 kernels (VPMADDUBSW) sum u8 x s8 pairs in
# int16, which 8-bit weights can saturate. NNCF's default fixes only the layers a model input feeds.
OVERFLOW_FIX = {"cpu": "ENABLE"}


def quantise(model: "ov.Model", request: ConvertRequest, feeds: dict[str, str],
             batch: int | None) -> tuple["ov.Model", dict[str, Any]]:
    """`model` quantised to int8 by nncf.quantize on the first `calibration_samples` calibration samples (all
    of them: subset_size counts the items), with the quantisation facts for the artifact's meta."""
    openvino()  # telemetry off before nncf imports openvino_telemetry
    import nncf
    from nncf.quantization.advanced_parameters import AdvancedQuantizationParameters, OverflowFix, \
        QuantizationParameters
    from nncf.quantization.range_estimator import RangeEstimatorParametersSet

    nncf.set_log_level(logging.WARNING)
    options = request.step.options
    items = calibration_items(request, feeds, batch)
    method = options.get("method", "minmax")
    weights = {"weights_quantization_params": QuantizationParameters(per_channel=bool(options["per_channel"]))
               } if "per_channel" in options else {}
    fix = OVERFLOW_FIX.get(request.target)
    overflow = {"overflow_fix": OverflowFix[fix]} if fix else {}
    advanced = AdvancedQuantizationParameters(
        activations_range_estimator_params=getattr(RangeEstimatorParametersSet, RANGES[method]), **weights,
        **overflow)
    device = getattr(nncf.TargetDevice, DEVICES[request.target])
    quantised = nncf.quantize(model, nncf.Dataset(items), preset=getattr(nncf.QuantizationPreset, PRESET),
                              target_device=device, subset_size=len(items),
                              fast_bias_correction=FAST_BIAS_CORRECTION, advanced_parameters=advanced)
    return quantised, {"quantiser": f"nncf {installed_versions('nncf').get('nncf', '')}".strip(),
                       "method": method, "activation_ranges": RANGES[method], "preset": PRESET.lower(),
                       "weights": "per channel" if options.get("per_channel", True) else "per tensor",
                       "fast_bias_correction": FAST_BIAS_CORRECTION, "target_device": device.value,
                       "overflow_fix": OVERFLOW_FIX.get(request.target, "FIRST_LAYER").lower(),
                       "calibration_samples": sum(count(item) for item in items)}


def calibration_items(request: ConvertRequest, feeds: dict[str, str],
                      batch: int | None) -> list[dict[str, Any]]:
    """The calibration samples as NNCF's data items, each a feed of every graph input (`feeds`: source input
    name -> graph input name): batches of ITEM samples, or whole batches of a model's fixed batch size."""
    data = calibration_data(request, request.step)
    size = batch or ITEM
    n = count(data) - count(data) % batch if batch else count(data)
    if n == 0:
        raise ValueError(f"{request.source.label} takes batches of exactly {batch}: raise "
                         f"calibration_samples to at least {batch}")
    return [{feeds[name]: np.ascontiguousarray(array) for name, array in item.items()}
            for item in batches({name: array[:n] for name, array in data.items()}, size)]
