"""Errors raised by the solvers."""
from __future__ import annotations


class SolverError(RuntimeError):
    """A solver diverged or failed to converge.

    Carries where it happened: the step index, the simulated time (s) and the node (or
    problem) index, so that a failure is never a silent NaN.
    """

    def __init__(self, message: str, *, step: int | None = None, time: float | None = None,
                 node: int | None = None):
        where = ", ".join(
            f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in (("step", step), ("time", time), ("node", node)) if v is not None
        )
        super().__init__(f"{message} ({where})" if where else message)
        self.step, self.time, self.node = step, time, node
