"""Ahead-of-time compiled programs: a function traced for fixed input shapes with ``make_fx`` and
compiled by inductor, called through a thin wrapper.

``torch.compile`` guards every call (shapes, globals, grad mode) and wraps it in dynamo's and
autograd's machinery, about 30 us a call on these CPUs, which dominates small real-time steps (a
Cosserat shot at batch 1, a surrogate step). A program compiled here costs a few microseconds a
call; it is only valid for inputs of the shapes, strides and dtypes it was traced with (callers
key their programs on them) and it does not track gradients.
"""
from __future__ import annotations

import contextlib
import os
import warnings
from typing import Callable, Sequence
from unittest import mock

import torch
from torch import Tensor

__all__ = ["compile_program", "is_tracing", "tracing"]

_TRACING = [False]


def is_tracing() -> bool:
    """Whether code runs traced for a compiled program: under ``torch.compile``, or within :func:`tracing` (a
    program traced by ``make_fx``, :func:`compile_program`). Time-dependent loads take their tensor forms then (no
    branch on the time), and the small products of :mod:`physics.lie` their fusable ones."""
    return _TRACING[0] or torch.compiler.is_compiling()


@contextlib.contextmanager
def tracing():
    """:func:`is_tracing` is True within (for the LGVI's programs, :meth:`physics.lgvi.LGVI.compiled_rollout`)."""
    old, _TRACING[0] = _TRACING[0], True
    try:
        yield
    finally:
        _TRACING[0] = old


def compile_program(fn: Callable, inputs: Sequence[Tensor], gemm_templates: bool = False,
                    direct: bool = False, ahead_of_time: bool = True, fast_exp: bool = False,
                    vectorize: bool = True) -> Callable:
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
    ``torch._inductor.compile`` returns (an empty program 9 -> 4.5 us a call here). On the CPU, unless
    ``ahead_of_time`` is False, it is compiled ahead of time instead (AOTInductor, ``torch._inductor.aot_compile``)
    with inductor's memory planning: a shared library that holds its constants and makes one allocation a call for
    its intermediate buffers (each output has its own, so that outputs kept, a rollout's frames, keep nothing else),
    run by its model runner (the JIT wrapper turns every constant, two dozen in a Simulation III step, into a tensor
    handle at every call; ``docs/surrogates.md``, "Programs compiled ahead of time"), in a folder named for the
    graph and its constants' values (:func:`_library_dir`: programs that differ only in their constants, two models
    of one architecture, are two libraries), built once and loaded from there by later programs and processes. Its
    inputs' sizes and strides are checked as the JIT wrapper checks them (``AOTI_RUNTIME_CHECK_INPUTS``, set here
    unless set), strides of size-1 dimensions included. For the small programs of a real-time step; the Cosserat
    solver's long programs keep the default path.

    ``fast_exp``: the C++ programs' vectorised ``exp`` as ATen's inline ``exp_u20`` (a degree-5 polynomial after
    range reduction; documented to 20 units in the last place, measured to 3.7e-7 relative, 3 units, on [-80, 80];
    0 below -87.3 and ``FLT_MAX`` above 88.7, not inf; NaN not kept) instead of Sleef's function call (1 unit).
    ``exp`` carries every sigmoid and tanh of a compiled surrogate step (``node_lstm._program_sigmoid``): the
    two-image Simulation III carried step 67.0 -> 63.8 us (``scripts/bench/surrogate_program.py``, Sleef's call 13 %
    of the step in ``perf``). Ignored for CUDA programs (Triton's ``exp``). Ahead of time, each library has a folder
    of its own (:func:`_library_dir`); just in time, inductor's caches are bypassed.

    ``vectorize=False``: the C++ kernels as scalar loops (inductor's ``cpp.vec_isa_ok`` off), left to the C++
    compiler. For programs whose innermost dimension is a 3-vector or a 3 x 3 matrix (the LGVI's step): inductor
    vectorises that dimension with masked 16-lane vectors that use 3 of their lanes, where the compiler unrolls the
    scalar loop; the batched LGVI step ran 1.9-2.1x faster so (``scripts/bench/lgvi.py``, ``docs/lgvi_speed.md``)."""
    from torch.fx.experimental.proxy_tensor import make_fx
    if isinstance(inputs, Tensor) or not all(isinstance(x, Tensor) for x in inputs):  # types only: nothing is read
        # a lone tensor was traced as its rows ("Tracing expected 1 arguments but got 3"), a float failed in .device
        raise TypeError("compile_program: inputs must be a sequence of tensors, one per argument of fn, got "
                        f"{type(inputs).__name__ if isinstance(inputs, Tensor) else [type(x).__name__ for x in inputs]}")
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
    cpu = all(x.device.type == "cpu" for x in inputs)
    fast_exp = fast_exp and cpu  # Triton's exp on CUDA
    mode = ("aot" if ahead_of_time and cpu else "direct") if direct else "wrapped"
    options = {"max_fusion_size": 100000, "cpp_wrapper": True} if mode != "aot" else \
        {"max_fusion_size": 100000, "memory_planning": True, "memory_pool": "intermediates"}
    if not vectorize:
        options["cpp.vec_isa_ok"] = False
    if fast_exp and mode != "aot":  # apart from programs with Sleef's exp: the JIT caches are keyed on the graph
        options = {**options, "force_disable_caches": True}
    attempts = [options]
    if gemm_templates:
        attempts.insert(0, {**options, "freezing": True, "max_autotune": True, "max_autotune_gemm_backends": "CPP"})
    for i, opts in enumerate(attempts):
        if mode == "aot":  # a library of its own for each graph, its constants and options (see _library_dir)
            opts = {**opts, "aot_inductor.output_path": _library_dir(gm, inputs, opts, fast_exp)}
        try:
            with torch.no_grad(), _exp_u20() if fast_exp else contextlib.nullcontext():
                prog = _compile(gm, list(inputs), opts, mode)
            break
        except Exception as err:  # noqa: BLE001 - e.g. NoValidChoicesError: a product no template covers
            if i == len(attempts) - 1:
                raise
            warnings.warn(f"compile_program: C++ GEMM templates failed ({type(err).__name__}: {err}); "
                          "compiling with library matrix products instead", RuntimeWarning, stacklevel=2)
    if direct:
        call = prog if mode == "aot" else (lambda args, call=prog.current_callable: call(list(args)))
        if tensor_out[0]:
            return lambda *args: call(args)[0]
        return lambda *args: tuple(call(args))
    if not isinstance(next(n for n in gm.graph.nodes if n.op == "output").args[0], torch.fx.Node):
        return prog

    def single(*args):  # inductor hands some single-tensor programs back as a one-element list
        out = prog(*args)
        return out[0] if isinstance(out, (list, tuple)) else out
    return single


def _aot_library(gm, inputs: list, options: dict) -> str:
    """The path of the ahead-of-time library for ``gm`` in its folder (:func:`_library_dir`): the one built there
    before, named in the folder's ``library`` file once it was built, else a new build (a Simulation III step
    takes seconds, the LGVI's four steps half a minute: each program, process and test built its own before)."""
    folder = options["aot_inductor.output_path"]
    record = os.path.join(folder, "library")
    try:
        with open(record) as f:
            path = os.path.join(folder, f.read().strip())
        if os.path.isfile(path):
            return path
    except OSError:  # not built yet (or unreadable: build it again)
        pass
    path = torch._inductor.aot_compile(gm, tuple(inputs), options={**options, "aot_inductor.package": False})
    tmp = f"{record}.{os.getpid()}.tmp"  # written whole, then renamed: a reader sees no half name
    with open(tmp, "w") as f:
        f.write(os.path.relpath(path, folder))
    os.replace(tmp, record)
    return path


def _library_dir(gm, inputs, options: dict, fast_exp: bool) -> str:
    """The folder (in inductor's cache) of the ahead-of-time library for the traced graph ``gm``: named for a digest
    of its code, the values of its constants, the inputs' layout, the options, ``fast_exp``, the torch build and the
    CPU's vector instructions. Inductor names a library for its wrapper code alone, which is the same for graphs that
    differ only in their constants' values (two models of one architecture, two LGVIs of one rod under different
    forces) or in the ``exp`` generated, and a library loaded twice from one path in a process is the first one:
    before 2026-12-02 the second such program ran with the first one's constants."""
    import hashlib
    h = hashlib.sha256()
    for part in (torch.__version__, torch.__file__, torch.backends.cpu.get_cpu_capability(), gm.code,
                 repr(sorted(options.items())), str(fast_exp),
                 repr([(tuple(x.shape), x.stride(), str(x.dtype), str(x.device)) for x in inputs])):
        h.update(part.encode())
    for node in gm.graph.nodes:
        if node.op != "get_attr":
            continue
        value = gm
        for name in node.target.split("."):
            value = getattr(value, name)
        h.update(node.target.encode())
        if isinstance(value, Tensor):
            h.update(f"{tuple(value.shape)} {value.dtype}".encode())
            h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
        else:
            h.update(repr(value).encode())
    from torch._inductor.runtime.cache_dir_utils import cache_dir
    return os.path.join(cache_dir(), "cmlearn_programs", h.hexdigest()[:32])


def _exp_u20():
    """While compiling: inductor's vectorised C++ ``exp`` generated as ATen's ``Vectorized::exp_u20`` (scalar
    loops keep ``std::exp``)."""
    from torch._inductor.codegen.cpp import CppVecOverrides
    if not isinstance(CppVecOverrides.__dict__.get("exp"), staticmethod):  # another torch: compile as it is
        warnings.warn("compile_program: fast_exp needs inductor's CppVecOverrides.exp (torch 2.14); compiling with "
                      "its own exp", RuntimeWarning, stacklevel=3)
        return contextlib.nullcontext()
    return mock.patch.object(CppVecOverrides, "exp", staticmethod(lambda x: f"{x}.exp_u20()"))


def _compile(gm, inputs: list, options: dict, mode: str):
    """Inductor's program for the traced graph: ``"wrapped"``, ``torch._inductor.compile``'s; ``"direct"``, the
    compiled graph of ``compile_fx_inner`` (call its ``current_callable`` with a list of the inputs); ``"aot"``, the
    ``run(inputs) -> outputs`` of AOTInductor's model runner on the CPU."""
    if mode == "wrapped":
        return torch._inductor.compile(gm, inputs, options=options)
    if mode == "aot":
        os.environ.setdefault("AOTI_RUNTIME_CHECK_INPUTS", "1")  # read by each library at its first call
        return torch._C._aoti.AOTIModelContainerRunnerCpu(_aot_library(gm, inputs, options), 1).run
    from torch._inductor.compile_fx import compile_fx_inner
    with torch._inductor.config.patch(options):
        return compile_fx_inner(gm, inputs, cpp_wrapper=True, is_inference=True)
