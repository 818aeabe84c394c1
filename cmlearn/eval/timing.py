"""What the benchmarks share: the wall time of the LGVI on a scene, in blocks of one rollout continued from call to
call (their peer), and their last line, the results as JSON."""
from __future__ import annotations

import json
import math
import time
from typing import Callable

from physics.checks import check_integer


def json_line(result, digits: int = 6) -> str:
    """``result`` (nested dicts and lists) as one line of JSON, floats rounded to ``digits`` significant digits and
    non-finite ones written as strings (``"nan"``, ``"inf"``), which JSON has no numbers for. numpy scalars and
    arrays, and tensors, are written as the numbers they hold (json could not write them: a benchmark failed at its
    very end)."""
    def rounded(x):
        if hasattr(x, "tolist") and type(x).__module__.split(".")[0] in ("numpy", "torch"):
            x = x.tolist()  # a numpy scalar or array, a tensor: Python numbers and lists
        if isinstance(x, float):
            return float(f"{x:.{digits}g}") if math.isfinite(x) else str(x)
        if isinstance(x, (list, tuple)):
            return [rounded(v) for v in x]
        if isinstance(x, dict):
            return {k: rounded(v) for k, v in x.items()}
        return x
    return json.dumps(rounded(result))


def lgvi_blocks(scene, steps: int, compiled: bool, steps_per_call: int = 4) -> tuple[Callable[[], float], float, object]:
    """``(block, warm-up seconds, integrator)``: ``block()`` gives the seconds per simulated second of the eager (or
    compiled, ``steps_per_call`` steps a call: :meth:`physics.lgvi.LGVI.compiled_rollout`) LGVI over its next
    ``steps`` steps of ``scene``, one rollout continued from call to call from the scene's start; the warm-up (the
    compile, for the compiled path) runs a few steps of it beforehand, discarded. The integrator's
    ``eager_blocks`` (compiled) counts the calls of the last block stepped eagerly, where a field cache refreshed."""
    steps_per_call = check_integer("steps_per_call", steps_per_call)
    steps = check_integer("steps", steps)
    if steps % steps_per_call:
        raise ValueError(f"steps must be a positive multiple of steps_per_call={steps_per_call}, got {steps}")
    sim = scene.make_integrator()
    cfg = scene.initial_configuration()
    state = [sim.initial_state(p=cfg["p"], R=cfg.get("R"))]
    run = (lambda st, n: sim.compiled_rollout(st, n_steps=n, steps_per_call=steps_per_call)) if compiled else \
        (lambda st, n: sim.simulate(st, n_steps=n, record_every=n))
    t0 = time.perf_counter()
    run(state[0], 2 * steps_per_call)
    warm = time.perf_counter() - t0

    def block() -> float:
        t0 = time.perf_counter()
        state[0] = run(state[0], steps)[0]
        return (time.perf_counter() - t0) / (steps * scene.dt)
    return block, warm, sim
