"""Benchmark: the compiled surrogate step's program in its current form against the forms it replaced, same
process, interleaved.

    python scripts/bench/surrogate_program.py [--checkpoint checkpoints/semicircle.pt] [--quick]

The current form (``NodeLSTMSurrogate.forward(..., program=True)``, compiled by
:func:`physics.programs.compile_program` with ``direct=True`` as ``Surrogate.compile`` compiles it) computes the
LSTM's and the dense layers' sigmoid and tanh through ``exp``, the head's 3-output layer as a summed product
(:func:`cmlearn.models.node_lstm._program_mlp`) and each LSTM frame's gates in one product of the frame's features
and the last output against both weight matrices. Each peer differs from it in one thing:

* ``torch``: ``torch.sigmoid``, ``torch.tanh`` and the ``nn`` layers as they are (before 2026-11-29);
* ``current_wrapped``: called through the AOT-autograd wrappers of ``torch._inductor.compile`` (``direct=False``,
  before 2026-11-29, later);
* ``input_product_first``: the LSTM's input product for all frames first, then the recurrent products (the same);
* ``current_jit``: compiled by inductor's JIT C++ wrapper (``compile_fx_inner``) and called through its callable,
  not ahead of time (``ahead_of_time=False``, before 2026-11-30, later);
* ``current_sleef_exp``: ``exp`` as Sleef's function call, not ATen's inline ``exp_u20`` (``fast_exp=False``, before
  2026-11-30, later still).

Beside them, ``carried``: the rollout's step (``NodeLSTMSurrogate.carried_step``, as ``cmlearn.surrogate.Stepper``
runs it since 2026-11-30), which takes the LSTM states of the step before and runs only the newest frame through the
LSTM, at every position of the window at once; ``carried_jit``, the same through the JIT wrapper;
``carried_sleef_exp``, with Sleef's ``exp``.

All are compiled for a batch-1 step of Simulation III's held-out scene with one, two and four mirror images in use
(``use_symmetry`` of both mirrors, of x alone, of none). Each figure is the fastest of ``--rounds`` means of
``--calls`` calls, the programs timed in turn, so that a machine whose speed drifts (these shared CPUs drift by up
to 2x over minutes) slows all alike. Last line: one JSON object. ``--quick``: one image, library matrix products
(faster compiles), fewer calls.
"""
from __future__ import annotations

import argparse
import functools
import platform
import time
from pathlib import Path

import torch

from cmlearn.args import bounded, readable
from cmlearn.eval.timing import json_line
from cmlearn.models import node_lstm
from cmlearn.surrogate import Surrogate
from physics.programs import compile_program

FORMS = {
    "current": (node_lstm._program_sigmoid, node_lstm._program_tanh, node_lstm._program_mlp, node_lstm._program_linear),
    "torch": (torch.sigmoid, torch.tanh, lambda seq, x: seq(x), lambda layer, x: layer(x)),
}


# name: (activations and layers, called directly, the LSTM's products stacked per frame, ahead of time, fast exp)
VARIANTS = {"current": ("current", True, True, True, True), "torch": ("torch", True, True, True, True),
            "current_wrapped": ("current", False, True, True, True),
            "input_product_first": ("current", True, False, True, True),
            "current_jit": ("current", True, True, False, True),
            "current_sleef_exp": ("current", True, True, True, False)}
CARRIED = {"carried": (True, True), "carried_jit": (False, True), "carried_sleef_exp": (True, False)}


def compile_form(model, form: str, args, gemm_templates: bool, direct: bool = True, stacked: bool = True,
                 ahead_of_time: bool = True, fast_exp: bool = True):
    """The model's program-form step compiled with the activations and layers of ``form``, called directly (ahead of
    time or through inductor's JIT wrapper) or through the wrappers of ``torch._inductor.compile``, its LSTM's
    products ``stacked`` per frame or not, with ATen's inline ``exp`` or Sleef's."""
    names = ("_program_sigmoid", "_program_tanh", "_program_mlp", "_program_linear")
    saved = [getattr(node_lstm, n) for n in names]
    for n, f in zip(names, FORMS[form]):
        setattr(node_lstm, n, f)
    model._lstm_last = functools.partial(type(model)._lstm_last, model, stacked=stacked)
    try:
        return compile_program(lambda h, w, r, *rest: model(h, w, r, program=True, rest=rest[0] if rest else None),
                               args, gemm_templates=gemm_templates, direct=direct, ahead_of_time=ahead_of_time,
                               fast_exp=fast_exp)
    finally:
        for n, f in zip(names, saved):
            setattr(node_lstm, n, f)
        del model._lstm_last


def interleaved_us(calls: dict, rounds: int, n: int) -> dict:
    """The fastest of ``rounds`` means of ``n`` calls of each, in microseconds, the calls timed in turn."""
    best = {k: float("inf") for k in calls}
    for f in calls.values():
        for _ in range(20):
            f()
    for _ in range(rounds):
        for k, f in calls.items():
            t0 = time.perf_counter()
            for _ in range(n):
                f()
            best[k] = min(best[k], (time.perf_counter() - t0) / n * 1e6)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=readable(),
                    default=str(Path(__file__).resolve().parents[2] / "checkpoints" / "semicircle.pt"))
    ap.add_argument("--scene", default="semicircle_heldout")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0, help="default 9 (3 with --quick)")
    ap.add_argument("--calls", type=bounded(int, at_least=0), default=0, help="default 400 (100 with --quick)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    a = ap.parse_args(argv)
    a.rounds, a.calls = a.rounds or (3 if a.quick else 9), a.calls or (100 if a.quick else 400)
    torch.set_num_threads(a.threads)
    engine = Surrogate.load(a.checkpoint)
    model = engine.model
    p0 = engine._initial_points(engine.task.scene_by_name(a.scene))
    gen = torch.Generator().manual_seed(0)
    K, W = model.idx_modeled.numel(), model.config.eta + 1
    hist = (p0[None, None].expand(1, W, -1, -1) + 1e-3 * torch.randn(1, W, *p0.shape, generator=gen)).contiguous()
    wrench = 0.01 * torch.randn(1, K, 3, generator=gen)
    ref = p0[None].clone()
    mirrors = tuple(axis for axis, _ in model.config.reflections)
    settings = [mirrors] if a.quick or len(mirrors) != 2 else [mirrors, mirrors[-1:], ()]
    rounds, n = a.rounds, a.calls
    res = {"checkpoint": a.checkpoint, "scene": a.scene, "threads": a.threads, "batch": 1, "dtype": "float32",
           "rounds": rounds, "calls": n, "gemm_templates": not a.quick, "platform": platform.platform(), "images": {}}
    for axes in settings:
        model.use_symmetry(axes)
        rest = engine.rest_accel(ref)
        args = [hist, wrench, ref] + ([] if rest is None else [rest])
        with torch.no_grad():
            want = model(hist, wrench, ref, rest=rest)
        progs = {k: compile_form(model, form, args, not a.quick, *how) for k, (form, *how) in VARIANTS.items()}
        st = engine.stepper(hist, ref)  # the rollout's states after hist[:, -2], and its rest output
        cargs = [*st.state, st.frames, wrench, ref, st.rest]
        carried = {k: compile_program(lambda *c: model.carried_step(*c, program=True), cargs,
                                      gemm_templates=not a.quick, direct=True, ahead_of_time=aot, fast_exp=fast)
                   for k, (aot, fast) in CARRIED.items()}
        dev = {k: float((p(*args) - want).abs().max()) for k, p in progs.items()}
        dev.update({k: float((p(*cargs)[0] - want).abs().max()) for k, p in carried.items()})
        calls = {k: (lambda p, x: lambda: p(*x))(p, args) for k, p in progs.items()}
        calls.update({k: (lambda p: lambda: p(*cargs))(p) for k, p in carried.items()})
        us = interleaved_us(calls, rounds, n)
        images = model.img_sign.shape[0]
        res["images"][str(images)] = {"axes": list(axes), "current_us": us["current"], "torch_us": us["torch"],
                                      "current_wrapped_us": us["current_wrapped"],
                                      "input_product_first_us": us["input_product_first"],
                                      "carried_us": us["carried"], "current_jit_us": us["current_jit"],
                                      "carried_jit_us": us["carried_jit"],
                                      "current_sleef_exp_us": us["current_sleef_exp"],
                                      "carried_sleef_exp_us": us["carried_sleef_exp"],
                                      "time_ratio": us["current"] / us["torch"],
                                      "direct_call_saves_us": us["current_wrapped"] - us["current"],
                                      "max_abs_vs_eager_m": dev}
        print(f"{images} of {model.mirror_sign.shape[0]} images: current {us['current']:.1f} us, torch's "
              f"{us['torch']:.1f} us ({100 * (1 - us['current'] / us['torch']):.0f} % less time); the current form "
              f"called through the wrappers {us['current_wrapped']:.1f} us, with the LSTM's input product first "
              f"{us['input_product_first']:.1f} us, through inductor's JIT wrapper {us['current_jit']:.1f} us, "
              f"with Sleef's exp {us['current_sleef_exp']:.1f} us; the rollout's carried step {us['carried']:.1f} us "
              f"(JIT wrapper {us['carried_jit']:.1f} us, Sleef's exp {us['carried_sleef_exp']:.1f} us); "
              f"max |compiled - eager| "
              + " / ".join(f"{v:.1e}" for v in dev.values()) + " m", flush=True)
    model.use_symmetry(())
    print(json_line(res, digits=17))
    return res


if __name__ == "__main__":
    main()
