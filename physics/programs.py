"""Ahead-of-time compiled programs: a function traced for fixed input shapes with ``make_fx`` and
compiled by inductor, called through a thin wrapper.

``torch.compile`` guards every call (shapes, globals, grad mode) and wraps it in dynamo's and
autograd's machinery, about 30 us a call on these CPUs, which dominates small real-time steps (a
Cosserat shot at batch 1, a surrogate step). A program compiled here costs a few microseconds a
call; it is only valid for inputs of the shapes, strides and dtypes it was traced with (callers
key their programs on them) and it does not track gradients.
"""
from __future__ import annotations

import warnings
from typing import Callable, Sequence

import torch
from torch import Tensor

__all__ = ["compile_program"]


def compile_program(fn: Callable, inputs: Sequence[Tensor], gemm_templates: bool = False,
                    direct: bool = False) -> Callable:
    """``make_fx`` (fake tensors; tensors held by ``fn`` itself, e.g. module weights, become constants)
    + ``torch._inductor.compile`` of ``fn(*inputs)`` for these shapes. oneDNN is off while tracing,
    so that an LSTM decomposes into matrix products and pointwise gates that inductor fuses, instead
    of staying one opaque ``mkldnn_rnn`` call.

    ``gemm_templates``: freeze the constants and generate each matrix product as inductor's C++
    micro-GEMM with its pointwise epilogue fused (``max_autotune`` with the ``CPP`` backend only, so
    nothing else is benchmarked): for products of a few tens of rows against constant weights this
    removes the BLAS call and bias copy of each one (a surrogate step 68 -> 52 us here) at several
    seconds more compile time. Where a product has no template, the program is compiled without.

    ``direct``: trace with inductor's decompositions and compile with ``compile_fx_inner``, called
    through the compiled graph's own callable, without the AOT-autograd runtime wrappers around what
    ``torch._inductor.compile`` returns (an empty program 9 -> 4.5 us a call here). For the small
    programs of a real-time step; the Cosserat solver's long programs keep the default path."""
    from torch.fx.experimental.proxy_tensor import make_fx
    tensor_out = []

    def traced(*args):  # compile_fx_inner compiles graphs that return a tuple
        out = fn(*args)
        tensor_out.append(isinstance(out, Tensor))
        return (out,) if tensor_out[-1] else tuple(out)
    # one tensor passed as two inputs would be traced as one input, read where either is: trace distinct copies
    inputs = [x.clone() if any(x is y for y in inputs[:i]) else x for i, x in enumerate(inputs)]
    extra = {}
    if direct:
        from torch._inductor.decomposition import select_decomp_table
        extra = {"decomposition_table": select_decomp_table()}
    onednn = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False
    try:
        with torch.no_grad():
            gm = make_fx(traced if direct else fn, tracing_mode="fake", _allow_non_fake_inputs=True, **extra)(*inputs)
    finally:
        torch.backends.mkldnn.enabled = onednn
    options = {"max_fusion_size": 100000, "cpp_wrapper": True}
    attempts = [options]
    if gemm_templates:
        attempts.insert(0, {**options, "freezing": True, "max_autotune": True, "max_autotune_gemm_backends": "CPP"})
    for opts in attempts:
        try:
            with torch.no_grad():
                prog = _compile(gm, list(inputs), opts, direct)
            break
        except Exception as err:  # noqa: BLE001 - e.g. NoValidChoicesError: a product no template covers
            if opts is attempts[-1]:
                raise
            warnings.warn(f"compile_program: C++ GEMM templates failed ({type(err).__name__}: {err}); "
                          "compiling with library matrix products instead", RuntimeWarning, stacklevel=2)
    if direct:
        call = prog.current_callable
        if tensor_out[0]:
            return lambda *args: call(list(args))[0]
        return lambda *args: tuple(call(list(args)))
    if not isinstance(next(n for n in gm.graph.nodes if n.op == "output").args[0], torch.fx.Node):
        return prog

    def single(*args):  # inductor hands some single-tensor programs back as a one-element list
        out = prog(*args)
        return out[0] if isinstance(out, (list, tuple)) else out
    return single


def _compile(gm, inputs: list, options: dict, direct: bool):
    """Inductor's program for the traced graph: ``torch._inductor.compile``, or ``direct`` the compiled graph
    of ``compile_fx_inner`` (call its ``current_callable`` with a list of the inputs)."""
    if not direct:
        return torch._inductor.compile(gm, inputs, options=options)
    from torch._inductor.compile_fx import compile_fx_inner
    with torch._inductor.config.patch(options):
        return compile_fx_inner(gm, inputs, cpp_wrapper=True, is_inference=True)
