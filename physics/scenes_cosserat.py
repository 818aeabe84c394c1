"""The magnetic continuum manipulator of Paper II (thesis lines 1822-1838, Figure II.9) as a static
Cosserat scene, and a linear (eMNS-style) field model for it.

Printed: a PMC-770 urethane body (rho 1000 kg/m^3, E 2.5 MPa, nu 0.5) with two embedded NdFeB block
magnets, N45 at the tip (distal) and N42 at an intermediate position (proximal), both rho 7000,
E 41.4 GPa, nu 0.3; dipole moments from the magnets' volume and remanence (``m = Br V / mu0``);
13 nodes for the Cosserat model; gravity acts; 6 stationary electromagnets around a 100 mm
spherical workspace. The dimensions were in Figure II.9(A), which is lost.

Chosen here: a 50 mm rod of 2 mm x 2 mm square section (a "beam"), made of four segments:
PMC 0-22 mm, proximal magnet 22-25 mm, PMC 25-47 mm, distal magnet 47-50 mm; the magnets are
2 x 2 x 3 mm blocks in line with the body (same section), axially magnetised along body +E3,
Br 1.30 T (N42, middle of 1.28-1.32) and 1.345 T (N45, middle of 1.32-1.37), moments 0.0124 and
0.0128 A m^2 at the magnet centres (s = 23.5 and 48.5 mm). The rod hangs: clamped at the origin
pointing down (-z, base quaternion ``(0, 1, 0, 0)``, a half turn about x) with gravity
``(0, 0, -9.81)``. With ``E I = 3.3e-6 N m^2`` a 20 mT field across the rod turns the tip magnet by
tens of degrees and gravity alone shortens nothing visibly (tension), which suits the workspace.

Loading: the magnets are :class:`~physics.cosserat.MagnetDipole` s (a field hook, e.g. from
:mod:`physics.magnetics` or :class:`LinearField`, evaluated at the solved poses), and the magnet
centres are also ``load_points`` for given dead wrenches (the thesis's Figure II.13 experiment
assigns known ``tau_m``, ``f_m``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import torch
from torch import Tensor

from .cosserat import CosseratRod, MagnetDipole, Segment
from .cosserat_shooting import CosseratSolver, StaticSolution
from .rod import Material, SquareSection
from .scene import G_EARTH, dipole_moment

__all__ = ["CosseratScene", "LinearField", "paper2_magnetic_rod", "PMC770", "NDFEB"]

PMC770 = Material(E=2.5e6, density=1000.0, nu=0.5)
NDFEB = Material(E=41.4e9, density=7000.0, nu=0.3)
BR_N42, BR_N45 = 1.30, 1.345  # T, middles of the grades' ranges
_EDGE, _BODY, _MAG = 2e-3, 22e-3, 3e-3


class LinearField:
    """``B(x) = B0 + G (x - x0)`` with constant gradient ``G[i, j] = dB_i/dx_j`` (..., 3, 3): the
    field of an electromagnetic navigation system linearised about ``x0`` (Maxwell: ``G``
    symmetric and traceless for a current-free region; not enforced). Hook: ``field(t, x) -> (B, dB)``."""

    def __init__(self, B0, G=None, x0=(0.0, 0.0, 0.0)):
        self.B0 = torch.as_tensor(B0)
        self.G = torch.zeros(3, 3, dtype=self.B0.dtype) if G is None else torch.as_tensor(G)
        self.x0 = torch.as_tensor(x0, dtype=self.B0.dtype)
        for nm, v, shape in (("B0", self.B0, "(..., 3)"), ("G", self.G, "(..., 3, 3)"), ("x0", self.x0, "(3,)")):
            want = (3,) if nm != "G" else (3, 3)
            if v.shape[max(v.dim() - len(want), 0):] != want or (nm == "x0" and v.dim() != 1) \
                    or not bool(torch.isfinite(v).all()):
                raise ValueError(f"LinearField.{nm} must be finite with shape {shape}, got shape {tuple(v.shape)}"
                                 f"{'' if bool(torch.isfinite(v).all()) else ' with non-finite values'}")
        try:  # (a batch of B0 and one of G that do not broadcast failed in torch at the first solve)
            torch.broadcast_shapes(self.B0.shape[:-1], self.G.shape[:-2])
        except RuntimeError:
            raise ValueError(f"LinearField: the batch shapes of B0 {tuple(self.B0.shape)} and G {tuple(self.G.shape)} "
                             f"do not broadcast") from None

    def __call__(self, t, positions: Tensor):
        B0, G = self.B0.to(positions), self.G.to(positions)  # the points' dtype and device
        d = positions - self.x0.to(positions)
        B = B0.unsqueeze(-2) + (G.unsqueeze(-3) * d.unsqueeze(-2)).sum(-1)
        shape = torch.broadcast_shapes(B.shape, positions.shape)
        return B.expand(shape), G.unsqueeze(-3).expand(*shape, 3)


@dataclass(frozen=True)
class CosseratScene:
    """A static Cosserat set-up: rod, gravity, base pose, printed (``thesis``) and ``chosen`` values."""

    name: str
    description: str
    rod: CosseratRod
    gravity: tuple[float, float, float] = (0.0, 0.0, -G_EARTH)
    base_quaternion: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    thesis: Mapping = field(default_factory=dict)
    chosen: Mapping = field(default_factory=dict)

    def solver(self, **kw) -> CosseratSolver:
        """A :class:`~physics.cosserat_shooting.CosseratSolver` for the rod (keywords go to it)."""
        return CosseratSolver(self.rod, **kw)

    def solve(self, solver: CosseratSolver | None = None, **kw) -> StaticSolution:
        """Solve with the scene's gravity and base pose (override them with ``gravity=``,
        ``base_quaternion=``); other keywords go to :meth:`CosseratSolver.solve`."""
        solver = self.solver() if solver is None else self._own(solver)
        return solver.solve(**self._posed(kw))

    def frame_solve(self, solver: CosseratSolver, **kw):
        """A :class:`~physics.cosserat_frames.FrameSolve` (a real-time loop's repeated solve) with the scene's
        gravity and base pose (override them as in :meth:`solve`); other keywords go to it."""
        from .cosserat_frames import FrameSolve
        return FrameSolve(self._own(solver), **self._posed(kw))

    def _own(self, solver) -> CosseratSolver:
        """``solver`` unless it is no :class:`CosseratSolver` or one for another rod (that rod was solved, with this
        scene's gravity and base pose, without a word)."""
        if not isinstance(solver, CosseratSolver):
            raise TypeError(f"solver must be a CosseratSolver, got {type(solver).__name__}")
        if solver.rod is not self.rod and solver.rod != self.rod:
            raise ValueError(f"solver: it was made for another rod than this scene's ({self.name}; the solver's rod "
                             f"has n_nodes={solver.rod.n_nodes}, the scene's {self.rod.n_nodes}): make it with "
                             f"scene.solver()")
        return solver

    def _posed(self, kw: dict) -> dict:
        """``kw`` with the scene's gravity and base pose where it does not give them (nor ``loads=``)."""
        if "loads" in kw:
            return kw
        return {"gravity": self.gravity, "base_quaternion": self.base_quaternion, **kw}


def paper2_magnetic_rod(n_nodes: int = 13) -> CosseratScene:
    """The Paper II manipulator (module docstring) on an RK4 grid of ``n_nodes`` nodes (>= 7)."""
    sec = SquareSection(_EDGE)
    vol = _EDGE * _EDGE * _MAG
    m42, m45 = dipole_moment(BR_N42, vol), dipole_moment(BR_N45, vol)
    s_prox, s_dist = _BODY + _MAG / 2, 2 * _BODY + 1.5 * _MAG
    rod = CosseratRod(
        segments=(Segment(_BODY, sec, PMC770, name="body 1"), Segment(_MAG, sec, NDFEB, name="proximal magnet (N42)"),
                  Segment(_BODY, sec, PMC770, name="body 2"), Segment(_MAG, sec, NDFEB, name="distal magnet (N45)")),
        n_nodes=n_nodes,
        magnets=(MagnetDipole(s_prox, (0.0, 0.0, m42), name="proximal N42"),
                 MagnetDipole(s_dist, (0.0, 0.0, m45), name="distal N45")),
        load_points=(s_prox, s_dist))
    return CosseratScene(
        name="paper2_magnetic_rod",
        description=__doc__.split("\n\n")[2].replace("\n", " "),
        rod=rod, base_quaternion=(0.0, 1.0, 0.0, 0.0),
        thesis={"body": {"E": 2.5e6, "density": 1000.0, "nu": 0.5}, "magnets": {"E": 41.4e9, "density": 7000.0,
                "nu": 0.3, "grades": ("N42 proximal", "N45 distal")}, "n_nodes": 13, "bandwidth_hz": (8.33, 50.0),
                "workspace_diameter": 0.1},
        chosen={"length": 2 * (_BODY + _MAG), "section": "square 2 mm", "magnet_block": (2e-3, 2e-3, 3e-3),
                "magnet_centres": (s_prox, s_dist), "Br": (BR_N42, BR_N45), "moments": (m42, m45),
                "magnetisation": "axial, body +E3", "base": "clamped at the origin pointing down (-z)"})
