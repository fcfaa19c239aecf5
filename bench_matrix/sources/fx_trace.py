"""FX graph mode preparation (torch.ao quantisation) of a PyTorch module: traced by torch.fx (a Hugging Face
transformers model it cannot trace, by transformers' own tracer); a failure is one line naming the tracer."""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from bench_matrix.sources.torch_files import brief

if TYPE_CHECKING:
    import torch

HF_TRACER = "transformers.utils.fx.symbolic_trace"


def fx_prepare(prepare: Callable[..., Any], module: "torch.nn.Module", mapping: Any,
               example: tuple["torch.Tensor", ...], label: str) -> "torch.fx.GraphModule":
    """`prepare(module, mapping, example_inputs=example)` (torch.ao's prepare_fx or prepare_qat_fx);
    ValueError, one line naming the tracer and its message, when no tracer can trace the module."""
    try:
        with _buffers_traced():
            prepared = prepare(module, mapping, example_inputs=example)
    except Exception as exc:  # symbolic tracing fails on data-dependent Python control flow
        failed = f"torch.ao.quantization {prepare.__name__}: torch.fx cannot trace {label}: {brief(exc)}"
        if type(module).__module__.partition(".")[0] != "transformers":
            raise ValueError(failed) from exc
        prepared = _by_transformers(prepare, module, mapping, example, failed)
    return _floats_observed(prepared, example)


def _by_transformers(prepare: Callable[..., Any], module: "torch.nn.Module", mapping: Any,
                     example: tuple["torch.Tensor", ...], failed: str) -> "torch.fx.GraphModule":
    """`prepare` of the module as transformers' own FX tracer, which knows its models' control flow, traces
    it on forward's inputs."""
    try:
        from transformers.utils.fx import symbolic_trace
    except ImportError as exc:
        raise ValueError(f"{failed}; it is a Hugging Face transformers model, whose own tracer ({HF_TRACER}) "
                         f"cannot be imported here ({brief(exc)}); install transformers, or quantise the "
                         f"model with the onnxruntime backend") from exc
    names = list(inspect.signature(module.forward).parameters)  # the inputs, as for_inputs passes them
    try:
        traced = symbolic_trace(module, input_names=names)
    except Exception as exc:  # a model class transformers' tracer does not support
        raise ValueError(f"{failed}; {HF_TRACER} cannot trace it either: {brief(exc)}") from exc
    try:
        with _buffers_traced():  # the graph reads its buffers as transformers' tracer did: as graph values
            return prepare(_dtypes_fixed(traced, example), mapping, example_inputs=example)
    except Exception as exc:  # the traced graph holds what the quantiser cannot handle
        raise ValueError(f"{failed}; as traced by {HF_TRACER} instead: {brief(exc)}") from exc


def _dtypes_fixed(traced: "torch.fx.GraphModule",
                  example: tuple["torch.Tensor", ...]) -> "torch.fx.GraphModule":
    """`traced` with each `.dtype` it reads (BERT's torch.finfo(hidden.dtype)) replaced by the dtype one run
    finds: torch.finfo refuses a traced dtype when torch.ao traces the graph again."""
    import torch

    reads = [n for n in traced.graph.nodes if n.op == "call_function" and n.target is getattr
             and n.args[1:] == ("dtype",)]
    found: dict[Any, Any] = {}

    class Dtypes(torch.fx.Interpreter):
        def run_node(self, n: torch.fx.Node) -> Any:
            found[n] = value = super().run_node(n)
            return value

    with torch.no_grad():
        Dtypes(traced).run(*example)
    for node in reads:
        for user in list(node.users):
            user.args, user.kwargs = torch.fx.node.map_aggregate(
                (user.args, user.kwargs), lambda a, n=node: found[n] if a is n else a)
        traced.graph.erase_node(node)
    traced.recompile()
    return traced


@contextmanager
def _buffers_traced() -> Iterator[None]:
    """torch.ao's tracer proxies buffers as it does parameters: a buffer sliced by a traced size (BERT's
    position_ids[:, :seq_len]) is traced, not sliced in Python ('slice indices must be integers')."""
    from torch.ao.quantization.fx.tracer import QuantizationTracer

    QuantizationTracer.proxy_buffer_attributes = True
    try:
        yield
    finally:
        del QuantizationTracer.proxy_buffer_attributes  # back to torch.fx's default, the base class's


def _floats_observed(prepared: "torch.fx.GraphModule",
                     example: tuple["torch.Tensor", ...]) -> "torch.fx.GraphModule":
    """`prepared` without the observers FX put on integer tensors (an attention mask, and what is computed
    from it before a cast), which cannot be quantised: FX does not know dtypes; one float run tells them."""
    import torch
    from torch.ao.quantization import FakeQuantizeBase, ObserverBase

    observed: dict[str, bool] = {}

    class Dtypes(torch.fx.Interpreter):
        def call_module(self, target: Any, args: Any, kwargs: Any) -> Any:
            if isinstance(self.fetch_attr(target), (ObserverBase, FakeQuantizeBase)):  # passed by
                observed[target] = isinstance(args[0], torch.Tensor) and args[0].is_floating_point()
                return args[0]
            return super().call_module(target, args, kwargs)

    training = prepared.training
    with torch.no_grad():  # in eval mode: batch norm's running statistics stay as they are
        Dtypes(prepared.eval()).run(*example)
    prepared.train(training)
    integer = [n for n in prepared.graph.nodes if n.op == "call_module" and observed.get(n.target) is False]
    for node in integer:
        node.replace_all_uses_with(node.args[0])
        prepared.graph.erase_node(node)
        prepared.delete_submodule(node.target)
    prepared.recompile()
    return prepared
