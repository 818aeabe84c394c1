"""The :class:`Scene` spec: a named, documented simulation set-up in SI units.

A scene bundles a :class:`~physics.rod.Rod`, boundary condition, time step, duration, gravity,
external loads (time-dependent node forces, a magnetic-field hook), an initial-configuration
builder, the nodes of interest, and ``thesis``: the values printed in the thesis for comparison
(converted to SI). Values the thesis does not give are chosen, kept in ``chosen`` and explained in
``description``. Build an integrator with :meth:`Scene.make_integrator` and a start state with
:meth:`Scene.initial_state`.

Thesis tables I.3-I.7 print the rod parameters axis-first (``E3 = [1, 0, 0]``) in an mg-mm-s
system (M in g/mm, which is the same number in kg/m); :func:`table_to_si` converts them to SI in
this package's (E1, E2, E3) order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping

import torch
from torch import Tensor

from .lgvi import LGVI, Boundary, LGVIState
from .loads import Loads
from .rod import Rod
from .magnetics.dipole import MU0, moment_from_remanence

__all__ = ["Scene", "table_to_si", "MU0", "G_EARTH", "dipole_moment"]

G_EARTH = 9.81  # m/s^2

# mg-mm-s -> SI factors
_LINE_INERTIA = 1e-9  # mg mm (J per unit length) -> kg m
_FORCE = 1e-9  # mg mm / s^2 -> N
_BENDING = 1e-15  # mg mm^3 / s^2 -> N m^2
_LINE_LOAD = 1e-6  # mg / s^2 (force per length) -> N/m


def _axis_first_to_e123(v):
    """(axis, lateral, lateral) as printed with E3 = [1, 0, 0] -> (E1, E2, E3)."""
    return (v[1], v[2], v[0])


def table_to_si(*, table: str, n_elements: int, M: float, J_d, C1, C2, F_c, dt: float,
                duration: float, **extra) -> dict:
    """Convert one of Tables I.3-I.7 (printed numbers, mantissas times powers of ten as printed)
    to SI in (E1, E2, E3) order: M kg/m, J_d kg m (line inertia), C1 N, C2 N m^2, F_c N/m (the
    gravity line load ``M g`` of the printed ``F^c``; a dict for per-node values)."""
    fc = {k: v * _LINE_LOAD for k, v in F_c.items()} if isinstance(F_c, dict) else F_c * _LINE_LOAD
    return dict(
        table=table, n_elements=n_elements, M=M,  # g/mm == kg/m
        J_d=tuple(x * _LINE_INERTIA for x in _axis_first_to_e123(J_d)),
        C1=tuple(x * _FORCE for x in _axis_first_to_e123(C1)),
        C2=tuple(x * _BENDING for x in _axis_first_to_e123(C2)),
        F_c=fc, dt=dt, duration=duration, **extra,
    )


def dipole_moment(Br: float, volume: float) -> float:
    """Dipole moment magnitude m = Br V / mu0 (A m^2) of a magnet of remanence Br (T), volume V (m^3)."""
    return moment_from_remanence(Br, volume)


InitialBuilder = Callable[[Rod], Mapping[str, Tensor]]


def _straight(rod: Rod) -> dict:
    s = rod.arclength
    p = torch.zeros(rod.n_nodes, 3, dtype=torch.float64)
    p[:, 2] = s
    return {"p": p}


@dataclass(frozen=True)
class Scene:
    """A named simulation set-up (SI units). See the module docstring.

    ``initial(rod)`` returns a mapping with ``p`` (n, 3), optionally ``R`` (n, 3, 3), ``v`` (n, 3)
    world velocities and ``omega`` (n, 3) body angular velocities, float64.
    ``title`` is a one-line summary (default: the description's first sentence).
    ``nodes_of_interest`` are 0-based node indices (``node_labels`` name them); the first is the
    node a summary reports (the tip for cantilevers). ``thesis`` holds the printed values in SI,
    ``chosen`` the values chosen here where the thesis is silent (and derived limits).
    """

    name: str
    description: str
    rod: Rod
    bc: str
    dt: float
    duration: float
    title: str = ""
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    loads: Loads = field(default_factory=Loads)
    initial: InitialBuilder = _straight
    base_motion: Callable | None = None
    nodes_of_interest: tuple[int, ...] = ()
    node_labels: tuple[str, ...] = ()
    thesis: Mapping = field(default_factory=dict)
    chosen: Mapping = field(default_factory=dict)

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"Scene.name must be an identifier, got {self.name!r}")
        Boundary(self.bc)  # validates
        for nm in ("dt", "duration"):
            v = getattr(self, nm)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Scene.{nm} must be a finite positive number of seconds, got {v!r}")
        g = tuple(float(x) for x in self.gravity)
        if len(g) != 3:
            raise ValueError(f"Scene.gravity must be a 3-vector (m/s^2), got {self.gravity!r}")
        object.__setattr__(self, "gravity", g)
        if self.loads.gravity is None:
            object.__setattr__(self, "loads", replace(self.loads, gravity=g if any(g) else None))
        elif tuple(float(x) for x in torch.as_tensor(self.loads.gravity, dtype=torch.float64).tolist()) != g:
            raise ValueError("Scene.loads.gravity disagrees with Scene.gravity")
        n = self.rod.n_nodes
        nodes = tuple(int(i) for i in self.nodes_of_interest) or (n - 1,)
        if not all(0 <= i < n for i in nodes):
            raise ValueError(f"Scene.nodes_of_interest must lie in [0, {n - 1}], got {nodes}")
        object.__setattr__(self, "nodes_of_interest", nodes)
        labels = tuple(self.node_labels) or tuple(f"node {i}" for i in nodes)
        if len(labels) != len(nodes):
            raise ValueError("Scene.node_labels must name every node of interest")
        object.__setattr__(self, "node_labels", labels)

    # ------------------------------------------------------------------ summary
    @property
    def summary(self) -> str:
        """One line: the title, or the first sentence of the description."""
        return self.title or self.description.split(". ")[0].strip().rstrip(".") + "."

    @property
    def n_steps(self) -> int:
        return int(round(self.duration / self.dt))

    @property
    def energy_conserved(self) -> bool:
        """True when the scene is conservative: no damping, no time-dependent or user loads, no
        field acting on magnets, no base motion (then LGVI energy should not drift)."""
        L = self.loads
        has_field = L.field is not None and len(self.rod.magnets) > 0
        return (self.rod.damping == 0 and self.rod.rotational_damping == 0 and L.force is None
                and L.torque is None and not has_field and self.base_motion is None)

    def stability(self) -> dict:
        """dt against the linearised explicit-update limit of this scene's rod."""
        est = self.rod.stable_time_step()
        return {"dt": self.dt, "dt_max": est.dt_max, "ratio": self.dt / est.dt_max, "limiting": est.limiting}

    # ------------------------------------------------------------------ integration
    def make_integrator(self, **overrides) -> LGVI:
        """An :class:`~physics.lgvi.LGVI` for this scene; keyword ``overrides`` replace any of its
        arguments (``dt``, ``dtype``, ``device``, ``stability``, ``loads``, ``rod``, ...)."""
        kw = dict(rod=self.rod, dt=self.dt, bc=self.bc, loads=self.loads, base_motion=self.base_motion)
        kw.update(overrides)
        return LGVI(**kw)

    def initial_configuration(self, rod: Rod | None = None) -> dict:
        """The initial positions/rotations/velocities (float64 tensors) from the builder, for the scene's rod
        or ``rod`` (e.g. a stiffer one: an equilibrium start is then that rod's, under the scene's loads)."""
        cfg = dict(self.initial(self.rod if rod is None else rod))
        unknown = set(cfg) - {"p", "R", "v", "omega"}
        if unknown:
            raise ValueError(f"scene {self.name}: initial builder returned unknown keys {sorted(unknown)}")
        return cfg

    def initial_state(self, integrator: LGVI | None = None, **overrides) -> LGVIState:
        """Initial :class:`~physics.lgvi.LGVIState` (made with ``integrator``, or with
        ``make_integrator(**overrides)``), built for the integrator's rod (the scene's loads give the start)."""
        if integrator is not None and overrides:
            raise ValueError(f"Scene.initial_state: give an integrator or the overrides {sorted(overrides)} for "
                             "make_integrator, not both (the overrides would be ignored)")
        integ = integrator if integrator is not None else self.make_integrator(**overrides)
        return integ.initial_state(**self.initial_configuration(integ.rod))
