"""The quasi-static hybrid in real time: one frame (20 ms on the magnetic rod) per call, from the coil currents alone.

:class:`QuasiStaticStepper` keeps what the next frame needs: the static rod's last solution, the static states
of the last ``increments + 1`` frames and the deviations of the last ``eta + 1``. A step

1. solves the static Cosserat rod (13 nodes, float64) at the new currents, started from the secant predictor
   ``2 w(k) - w(k-1)`` of the base wrench (two Levenberg-Marquardt iterations where the warm start alone took
   three, on the held-out profile) and, with ``chord`` (default), first by chord iterations with the secant of the
   last two frames' Jacobians (``CosseratSolver.solve(chord=...)``: shots without tangents, then one with them),
   in the stages of :data:`STAGES`: at most 10 iterations (with ``frame_solve``, the default, by a
   :class:`~physics.cosserat_frames.FrameSolve`, which looks the solver's compiled programs up once instead of at
   every frame), then, where the rod snaps over (its branch of equilibria ends at a fold), the loads stepped up from
   the predictor in 12 steps of at most 10 iterations each. On the held-out profile's folds that lands where the
   solver's own escalation
   lands (4, 16, then 64 load steps of up to 50 iterations each: 211-260 iterations, 44-54 ms), in at most 65
   iterations. Where the stages fail, that escalation, then the static track's own recovery from the last
   solution (:func:`cmlearn.data.quasistatic._warm_step`: the frame split in time, then a cold restart past a
   fold), the currents interpolated linearly within the frame; where no equilibrium is found at all, a
   :class:`~physics.errors.SolverError` names the step and time;
2. computes its stability margin, the static state, the correction's deviation
   (:class:`~cmlearn.models.QuasiStaticCorrection`, float32) and the magnets' poses; with ``compile``, one program
   compiled ahead of time (:func:`physics.programs.compile_program`) does all of it.

With ``compile`` the solver runs its compiled path in the coils' field tabulated over the workspace
(:func:`~cmlearn.surrogate.magnetic.field_table`, 1e-8 of the exact field); otherwise the exact coil model, eager.
Frame for frame it follows :meth:`~cmlearn.surrogate.quasistatic.QuasiStaticSurrogate.run` from rest (which solves
the static track offline, warm-started without the predictor): on the held-out profile to 1e-5 deg eagerly (its first
100 frames) and to 5e-4 deg compiled (all 1,200, snap-throughs included).
"""
from __future__ import annotations

import math
import time
import warnings

import torch
from torch import Tensor

from cmlearn.data.quasistatic import (_HALVINGS, TabulatedField, _warm_step, compose, field_hook, fold_clock_step,
                                      stability_margin, static_state, with_fold_clock)
from cmlearn.data.tasks import CURRENT_LIMIT
from cmlearn.models.quasistatic import QuasiStaticCorrection
from physics.cosserat_ode import quat_matrix
from physics.cosserat_shooting import StaticSolution
from physics.checks import check_integer
from physics.errors import SolverError

from .magnetic import field_table

__all__ = ["QuasiStaticStepper", "STAGES"]

#: The static solve's first tries, each (load steps, LM iterations allowed per load step), from the predictor.
STAGES = ((1, 10), (12, 10))


class QuasiStaticStepper:
    """``step(currents)`` -> the magnets' centres (2, 3) m and rotations (2, 3, 3) at the next frame, for coil
    ``currents`` (C,) A; ``reset(currents)`` puts the rod at rest (the static rod at those currents, no
    deviation). ``model``: the correction; ``rest``: the static rod's magnet rotations at zero current (2, 3, 3);
    ``emns``: the coils; ``pose``: the clamp (:func:`~cmlearn.surrogate.magnetic.base_pose`); ``delta``: the frame
    (s), for error messages; ``programs``: where the compiled correction is kept for the next stepper of the same
    ``model`` and ``rest``; ``stages``: the solve's first tries (:data:`STAGES`; ``()``: the solver's own escalation
    at once); ``tol``: the solve's bound on the scaled tip residual (default the solver's 1e-10, as the offline
    static track's; ``python scripts/report_hybrid_tolerance.py`` measures the frames' deviation and the step's time
    against it); ``chord``: chord iterations before the first stage's LM; ``frame_solve``: the first stage by a
    :class:`~physics.cosserat_frames.FrameSolve` (module docstring; off: the solver's call). The attributes ``static``
    and ``solution`` hold the last frame's static rod, ``iterations`` the chord and LM iterations of its solve's tries
    (of the fallback's sub-steps, the last one's). Currents beyond :data:`~cmlearn.data.tasks.CURRENT_LIMIT` A on
    any coil (outside the training profiles, where the correction extrapolates) warn once. ``max_seconds`` bounds a
    step's solve: past it a :class:`~physics.errors.SolverError` names the step and the stepper stays at its last
    frame (checked at every field evaluation eagerly, between solves when compiled; default unbounded: far outside the
    training currents, e.g. 1e4 A, the fallback's sub-steps were still searching after 14 minutes, eager)."""

    def __init__(self, model: QuasiStaticCorrection, rest: Tensor, emns, pose: dict, delta: float,
                 compile: bool = False, predictor: bool = True, programs: dict | None = None,
                 stages: tuple[tuple[int, int], ...] = STAGES, tol: float | None = None, chord: bool = True,
                 frame_solve: bool = True, max_seconds: float | None = None):
        from physics.scenes_cosserat import paper2_magnetic_rod
        ok = isinstance(max_seconds, (int, float)) and not isinstance(max_seconds, bool) and 0 < max_seconds < math.inf
        if max_seconds is not None and not ok:
            raise ValueError(f"max_seconds must be a finite number of seconds > 0 or None, got {max_seconds!r}")
        self.max_seconds = max_seconds
        try:  # checked here, not at the first step ("cannot unpack non-iterable int object" for a flat (1, 10))
            stages = tuple((check_integer("load steps", n), check_integer("iterations", i)) for n, i in stages)
        except (TypeError, ValueError) as e:
            raise ValueError(f"stages must be (load steps, iterations) pairs of integers >= 1, e.g. {STAGES}, got "
                             f"{stages!r} ({e})") from None
        self.model, self.rest, self.emns, self.pose, self.delta = model.eval(), rest, emns, pose, float(delta)
        self.sc = paper2_magnetic_rod(13)
        self.solver = self.sc.solver(compile=compile, **({} if tol is None else {"tol": tol}))
        self.nodes = list(self.sc.rod.grid.magnet_nodes)
        if compile:
            table = field_table(emns)
            self._field_of = lambda I: TabulatedField(table, I)  # noqa: E731
        else:
            self._field_of = lambda I: field_hook(emns, I)  # noqa: E731
        self._deadline = None
        self.predictor, self.compiled, self.stages, self.chord = predictor, compile, tuple(stages), bool(chord)
        self.frame_solve, self._frame_solves = bool(frame_solve), {}  # (per number of iterations allowed)
        with torch.no_grad():
            self._rest_out = model.rest_output()
        self._programs = {} if programs is None else programs
        self._warned = False
        self.reset()

    # ---------------------------------------------------------------------------------------------- state
    def reset(self, currents: Tensor | None = None):
        """At rest in the static rod at ``currents`` (default zero): solved cold with load stepping."""
        I = self._currents(currents if currents is not None else torch.zeros(self.emns.n_coils))
        self.solution = self.sc.solve(self.solver, field=self.field_of(I), load_steps=4, **self.pose)
        self.currents, self.k, self.iterations = I, 0, int(self.solution.iterations)
        self._prev_wrench = self._prev_jacobian = None
        c = self.model.config
        s = self._state(self.solution)
        self.static = s.expand(1, c.increments + 1, s.shape[-1]).clone()
        self.dev = torch.zeros(1, c.eta + 1, 12)

    def field_of(self, I: Tensor):
        """The field hook of currents ``I``; while a step's solve runs under ``max_seconds``, one that raises past
        it (the eager hook at every evaluation; the compiled solver's tabulated field, traced, as it is made)."""
        deadline = self._deadline
        if deadline is None:
            return self._field_of(I)
        self._check_deadline(deadline)
        hook = self._field_of(I)
        if self.compiled:
            return hook

        def timed(t, x):
            self._check_deadline(deadline)
            return hook(t, x)
        return timed

    def _check_deadline(self, deadline: float):
        if time.perf_counter() > deadline:
            raise SolverError(f"quasi-static step: no static equilibrium within max_seconds={self.max_seconds:g} s "
                              f"at currents {self._target} A; the stepper stays at its last frame",
                              step=self.k + 1, time=(self.k + 1) * self.delta)

    def _currents(self, currents) -> Tensor:
        I = torch.as_tensor(currents, dtype=torch.float64).detach()
        if I.shape != (self.emns.n_coils,):
            raise ValueError(f"currents must be {self.emns.n_coils} numbers (A), got shape {tuple(I.shape)}")
        if not all(map(math.isfinite, I.tolist())):
            raise ValueError(f"currents must be finite, got {I.tolist()}")
        if not self._warned and float(I.abs().max()) > CURRENT_LIMIT:
            self._warned = True
            warnings.warn(f"currents {I.tolist()} A exceed the +-{CURRENT_LIMIT:g} A per coil of the correction's "
                          "training profiles: the static rod is exact, the correction extrapolates (this stepper "
                          "warns once)", stacklevel=3)
        return I

    def _state(self, sol) -> Tensor:
        """The static state (1, 1, 13) of a solution at rest (with the fold clock at its cap, where the model reads
        it: 14 columns)."""
        P, R = sol.p[..., self.nodes, :], sol.R[..., self.nodes, :, :]
        s = static_state(P, R, self.rest, stability_margin(sol)).float()[None, None]
        cap = self.model.config.fold_clock
        return with_fold_clock(s, cap) if cap else s

    # ---------------------------------------------------------------------------------------------- a step
    def solve(self, currents) -> StaticSolution:
        """The static rod at ``currents`` (the next frame's), from the predictor or the last solution; it becomes
        :attr:`solution` (the correction is :meth:`correct`'s)."""
        I = self._currents(currents)
        if self.max_seconds is None:
            return self._solve(I)
        self._deadline, self._target = time.perf_counter() + self.max_seconds, I.tolist()
        try:
            return self._solve(I)
        finally:
            self._deadline = None

    def _solve(self, I: Tensor) -> StaticSolution:
        sol = self.solution
        secant = self._prev_wrench is not None and self.predictor
        init = torch.lerp(self._prev_wrench, sol.base_wrench, 2.0) if secant else sol  # 2 w(k) - w(k-1)
        jac = None  # the chord steps' Jacobian: the secant of the last two frames' where the predictor is
        if self.chord:
            jac = torch.lerp(self._prev_jacobian, sol.jacobian, 2.0) if secant else sol.jacobian
        field, self.iterations = self.field_of(I), 0
        for k, (steps, its) in enumerate(self.stages):
            if k == 0 and steps == 1 and self.frame_solve:  # the programs looked up once (physics.cosserat_frames)
                if its not in self._frame_solves:
                    self._frame_solves[its] = self.sc.frame_solve(self.solver, max_iter=its, **self.pose)
                out = self._frame_solves[its](field, init, jac)
            else:
                out = self.sc.solve(self.solver, field=field, init=init, load_steps=steps, max_load_steps=steps,
                                    max_iter=its, raise_on_failure=False, chord=jac if steps == 1 else None,
                                    **self.pose)
            self.iterations += int(out.iterations)
            if bool(out.converged.all()):
                break
        else:
            out = self.sc.solve(self.solver, field=field, init=init, raise_on_failure=False, **self.pose)
            self.iterations += int(out.iterations)
        if not bool(out.converged.all()):
            I0 = self.currents
            try:
                out = _warm_step(self.sc, self.solver, self.field_of, lambda u: I0 + u * (I - I0), self.pose, sol,
                                 0.0, 1.0, _HALVINGS)
            except SolverError as e:
                if self._deadline is not None and time.perf_counter() > self._deadline:
                    raise
                raise SolverError(f"quasi-static step: no static equilibrium at the new currents ({e})",
                                  step=self.k + 1, time=(self.k + 1) * self.delta) from None
            self.iterations += int(out.iterations)
        self._prev_wrench, self._prev_jacobian, self.solution, self.currents = sol.base_wrench, sol.jacobian, out, I
        return out

    @torch.no_grad()
    def correct(self) -> tuple[Tensor, Tensor]:
        """The correction on :attr:`solution`: the magnets' centres (2, 3) and rotations (2, 3, 3) of that frame."""
        sol = self.solution
        args = (sol.y.contiguous(), sol.jacobian.contiguous(), self.dev, self.static)
        frame = self._frame
        if self.compiled:
            frame = self._programs.get("frame")
            if frame is None:
                from physics.programs import compile_program
                frame = self._programs["frame"] = compile_program(self._frame, args, direct=True)
        self.dev, self.static, c, R = frame(*args)
        self.k += 1
        return c, R

    def _frame(self, y: Tensor, jacobian: Tensor, dev: Tensor, static: Tensor):
        """The correction's frame from the static solution's node states ``y`` (n, 13) and scaled Jacobian: the next
        deviations and static states, the magnets' centres and rotations."""
        y = y[self.nodes]
        q = y[:, 3:7]
        P, R = y[:, 0:3], quat_matrix(q / q.norm(dim=-1, keepdim=True))
        s = static_state(P, R, self.rest, stability_margin(jacobian)).float()[None, None]
        cap = self.model.config.fold_clock
        if cap:  # the clock of this frame from the last two frames' (cmlearn.data.quasistatic.fold_clock_step)
            tau = fold_clock_step(static[:, -1, 13], static[:, -1], s[:, 0], static[:, -2, 12], cap)
            s = torch.cat([s, tau[:, None, None]], -1)
        static = torch.cat([static[:, 1:], s], 1)
        d = self.model(dev, static, self._rest_out)
        c, Rm = compose(d[0], P, R)
        return torch.cat([dev[:, 1:], d[:, None]], 1), static, c, Rm

    def step(self, currents) -> tuple[Tensor, Tensor]:
        """The next frame at coil ``currents`` (C,) A: :meth:`solve`, then :meth:`correct`."""
        self.solve(currents)
        return self.correct()

    def __repr__(self) -> str:
        return f"QuasiStaticStepper(frame {self.k}, delta={self.delta:g} s, compiled={self.compiled})"
