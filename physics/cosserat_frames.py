"""The static solve of a real-time loop: one rod under the same loads solved at every frame in a new field of the
same kind (new coil currents), warm-started from the frame before (:class:`FrameSolve`).

:meth:`CosseratSolver.solve <physics.cosserat_shooting.CosseratSolver.solve>` checks its inputs, works out the
batch shape and looks its compiled programs up by their inputs' layout at every call. At batch 1 that took about as
long as the programs themselves on the Paper II rod (measured on the magnetic rod's real-time step: the programs of
a typical frame about 0.43 ms, the step 0.85 ms). A :class:`FrameSolve` does it once, at its first call, and keeps
the programs and their loop-invariant inputs; a call then flattens the new field, runs the chord program's blocks
and LM's programs, and builds the :class:`~physics.cosserat_shooting.StaticSolution`. It solves what
``solver.solve(field=field, init=init, chord=chord, load_steps=1, max_load_steps=1, max_iter=max_iter,
raise_on_failure=False, **loads)`` solves, with the same programs, so to the same numbers (``converged`` tells
whether it did; a loop escalates from there, :class:`cmlearn.surrogate.quasistatic_stepper.QuasiStaticStepper`).
Inputs that the fast path does not take (a solver without ``compile``, a field hook that cannot be traced, a field
of another structure than the first call's, tensors that require grad) go to that call instead.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .checks import check_integer
from .cosserat_fast import chord_setup, flatten_field, lm_setup, run_chord, run_lm
from .cosserat_shooting import (_LAM_WARM, CHORD_MAX, CosseratSolver, StaticSolution, _broadcasts_to, _needs_grad,
                                tensor_versions)

__all__ = ["FrameSolve"]


class FrameSolve:
    """``FrameSolve(solver, max_iter=None, t=0.0, **loads)``; ``frame(field, init, chord=None) -> StaticSolution``:
    one load step of at most ``max_iter`` iterations (default the solver's) from ``init`` (a
    :class:`~physics.cosserat_shooting.StaticSolution` or base wrench (..., 6) in SI), first chord iterations with
    ``chord`` (a nearby solution's scaled Jacobian (..., 6, 6)) where given (module docstring). ``loads``: keywords
    of :meth:`~physics.cosserat_shooting.CosseratSolver.make_loads` (or ``loads=`` a whole
    :class:`~physics.cosserat.StaticLoads`), fixed for every frame. ``compiled=False`` runs
    the same programs eagerly (tests)."""

    def __init__(self, solver: CosseratSolver, *, max_iter: int | None = None, t: float = 0.0, compiled: bool = True,
                 **loads):
        if not isinstance(solver, CosseratSolver):
            raise TypeError(f"solver must be a CosseratSolver, got {type(solver).__name__}")
        max_iter = check_integer("max_iter", solver.max_iter if max_iter is None else max_iter)
        self.solver, self.max_iter, self.t, self.load_kw = solver, max_iter, float(t), loads
        self.compiled = bool(compiled)
        if "loads" in loads:  # whole StaticLoads, as solve(loads=...) takes them (make_loads refused the keyword)
            if len(loads) > 1:
                raise ValueError(f"give the loads either as loads= or as keywords, not both (got loads= and "
                                 f"{', '.join(sorted(k for k in loads if k != 'loads'))}=)")
            self._loads = solver._check_loads(loads["loads"])
        else:
            self._loads = solver._loads(dict(loads))  # checked once (make_loads)
        self._fkey = None  # the field structure, shapes and solver parameters the programs below were set up for
        self._fprm = None
        self._chord = self._lm = None

    def __call__(self, field, init, chord: Tensor | None = None) -> StaticSolution:
        solver = self.solver
        flat = flatten_field(field) if solver.compile and solver.steps_per_call == 1 else None
        if flat is None or _needs_grad(tuple(self._loads), tuple(solver.params), field, *flat[1]):
            return self._solve(field, init, chord)  # (which adds the implicit gradients)
        w = init.base_wrench if isinstance(init, StaticSolution) else init
        if not isinstance(w, Tensor) or w.shape[-1:] != (6,) or (chord is not None and chord.shape[-2:] != (6, 6)) \
                or (field is not None and not solver.rod.magnets):
            return self._solve(field, init, chord)  # (which names what is wrong)
        key = flat[0], w.shape, chord is None or chord.shape, tensor_versions(solver.params)
        if (key != self._fkey or self._fprm is not solver.params) and not self._setup(field, flat, w, chord):
            return self._solve(field, init, chord)
        shp, N = self._shape, self._n
        ftens = [a.contiguous() for a in flat[1]]
        x = (w.detach().to(solver.dtype) / solver._sc).expand(*shp, 6).reshape(N, 6).contiguous()
        its = self._its0
        if chord is not None:
            Jinv, info = torch.linalg.inv_ex(chord.detach().to(solver.dtype))
            if not bool((info != 0).any()):  # (a singular Jacobian: no chord steps)
                prog, starts, fixed = self._chord
                Jinv = Jinv.expand(*shp, 6, 6).reshape(N, 6, 6).contiguous()
                x, its = run_chord(prog, starts, fixed + ftens, x, Jinv, its, (N,), min(CHORD_MAX, self.max_iter),
                                   solver.chord_block)
        chunks, starts, base, fixed = self._lm
        x, r, J, Y, rn, its = run_lm(chunks, starts, base, fixed + ftens, x, its, its + self.max_iter, self._live, shp,
                                     self._n_rec)
        return StaticSolution(solver._s, Y, x.reshape(*shp, 6) * solver._sc, rn <= solver.tol, its, rn, J)

    def _solve(self, field, init, chord) -> StaticSolution:
        """The general call (:meth:`CosseratSolver.solve`) of what a frame solves."""
        return self.solver.solve(field=field, t=self.t, init=init, chord=chord, load_steps=1, max_load_steps=1,
                                 max_iter=self.max_iter, raise_on_failure=False, **self.load_kw)

    def _setup(self, field, flat, w: Tensor, chord: Tensor | None) -> bool:
        """The programs and loop-invariant inputs for fields of ``flat``'s structure, starts shaped as ``w`` and
        chord Jacobians as ``chord`` (compiled where new); False where the fast path does not take them."""
        solver, loads, prm = self.solver, self._loads, self.solver.params
        solver._table(prm)
        x0 = torch.zeros(w.shape[:-1] + (6,), dtype=solver.dtype, device=solver.device)
        shp = tuple(solver._batch_shape(loads, prm, x0, field, self.t, flat))
        if chord is not None and not _broadcasts_to(chord.shape[:-2], shp):
            return False
        N = math.prod(shp)
        x = x0.expand(*shp, 6).reshape(N, 6).contiguous()
        its = torch.zeros(N, dtype=torch.long, device=solver.device)
        live = torch.ones(N, dtype=torch.bool, device=solver.device)
        eye = torch.eye(6, dtype=solver.dtype, device=solver.device).expand(N, 6, 6).contiguous()
        ch = chord_setup(solver, x, eye, prm, loads, field, self.t, its, its + min(CHORD_MAX, self.max_iter), live,
                         solver._step_tab, solver.chord_block, self.compiled, flat)
        lm = lm_setup(solver, x, prm, loads, field, self.t, its, _LAM_WARM, live, solver._step_tab, self.compiled,
                      flat, self.max_iter)
        if ch is None or lm is None:
            return False
        n_ftens = len(flat[1])
        prog, starts, fixed, _ = ch
        chunks, lm_starts, base, lm_fixed, _, n_rec = lm
        self._chord = prog, starts, fixed[:len(fixed) - n_ftens]  # (the field's tensors come with each call)
        self._lm = chunks, lm_starts, base, lm_fixed[:len(lm_fixed) - n_ftens]
        self._shape, self._n, self._n_rec, self._its0, self._live = shp, N, n_rec, its, live
        self._fkey = flat[0], w.shape, chord is None or chord.shape, tensor_versions(self.solver.params)
        self._fprm = self.solver.params
        return True
