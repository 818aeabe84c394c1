"""The Paper II magnetic rod (thesis II.5, Data-set IV) as a dynamic LGVI scene in the six-coil eMNS.

The rod is the one :func:`physics.scenes_cosserat.paper2_magnetic_rod` chose for the static Cosserat
model: 50 mm of PMC-770 (E 2.5 MPa, rho 1000, nu 0.5), 2 mm x 2 mm square section, with two
2 x 2 x 3 mm NdFeB blocks in line, the proximal (N42, 0.0124 A m^2) over 22-25 mm and the distal
(N45, 0.0128 A m^2) over 47-50 mm, both magnetised along body +E3; clamped at the origin hanging
down (body E3 = world -z, the base frame a half turn about x), gravity along -z. It sits in the
default six-coil eMNS (:func:`physics.magnetics.emns.six_coil_emns`), driven by time-varying coil
currents; the field reaches the magnets through :class:`physics.coil_currents.CoilField`.

Discretisation (chosen). 10 elements: each PMC part in 4 elements of 5.5 mm, each magnet one 3 mm
element, so the magnet blocks are whole elements, as in the Cosserat grid. The LGVI rod has one
material, so a magnet element is PMC whose bending and torsion stiffness C2 is multiplied by 20
(the block is rigid; 20x makes its bending compliance 0.3 % of the rod's while keeping the time
step; its axial and shear stiffness, already ~1e-4 strain here, stay PMC's). A magnet is a point
mass of the NdFeB minus the PMC it replaces ((7000 - 1000) kg/m^3 x 12 mm^3 = 72 mg) at the block
centre (xi = 0.5), carrying its dipole and the block's rotational inertia. Rotational inertia (rod
and blocks) is mass-scaled by 16 so that dt = 8e-5 s is stable (dt/dt_max 0.71); the first bending
frequency (4.15 Hz) changes by 0.8 %, the second (25.8 Hz) by 5 %, the first torsion mode drops from
95 to 24 Hz; the motion is slow (set-point moves), where rotational inertia plays little part. The printed
mesh's limit is then 0.11 ms; :func:`on_mesh` builds the rod with fewer elements in each PMC part (the work-precision
bench: 0.16 ms on 2 a part, 0.18 ms on 1).
Viscous damping 0.107 N s/m^2 and rotational damping 1.28e-5 N m s/m: 25 % of critical in the first
bending mode, 48 % in the first torsion mode, 8 % in the second bending mode (:func:`modal_damping`),
so that the rod settles within a hold and no fast torsion rings between the 50 Hz samples.

Currents (chosen; the thesis's experiment moved quasi-statically through 669 samples in 340 s).
Printed profile (``magnetic_rod``, 24 s): from rest at zero current, minimum-jerk moves of 1.5 s
with 1 s holds through the currents that give a 5 mT field midway between the magnets (0, 0, -36 mm) along
+x, +x+y, +y, -x, -x-y, -y, +x-y, +x again and back to zero (each the minimum-norm current vector
for the field alone, at most 2.7 A); at 5 mT along +x the proximal magnet settles 36 deg and the
distal 49 deg from the vertical. Held-out (``magnetic_rod_heldout``, 24 s): per coil a sum of three
sinusoids (0.06-0.25 Hz) faded in over 2 s, at most 4 A, a kind of profile never drawn for training
(training draws minimum-jerk moves between random current vectors; see :mod:`cmlearn.data.tasks`);
the magnets swing up to 50 and 56 deg and at two moments snap over quickly (a fold of the
equilibrium), where a static model cannot follow. The rod starts at rest hanging straight under
gravity (static equilibrium; zero current at t = 0).

Planar set-up (``magnetic_rod_planar``, chosen after the experiment of II.5.2, where the rod was
suspended horizontally along x and steered in a plane, orientations about y): the same rod clamped at
(-25, 0, 0) mm along +x (body E1 along -z), at rest sagging under gravity (tip 17 mm down, the magnets
23 and 28 deg below the horizontal). The currents are the minimum-norm ones for fields in the x-z plane
at (0, 0, -8) mm; the eMNS and these currents are mirror-symmetric about that plane, so the rod stays
in it. Printed profile (24 s): minimum-jerk moves (1.5 s, 1 s holds) to 6 mT at 30, 60, 90, 30, -30,
-60, -90, -30 deg from +x towards +z and back to zero (at most 5.5 A); the magnets then range over
about -52..+39 deg, and between 36 and 39 deg of field the sagging rod snaps up (a fold). Held-out
(``magnetic_rod_planar_heldout``): a field of 5 +- 1.5 mT sweeping through +-80 deg (two slow
sinusoids), never holding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from .coil_currents import CoilField, MinJerkCurrents, SinusoidCurrents, min_jerk
from .checks import check_integer
from .loads import Loads
from .magnetics.emns import six_coil_emns
from .programs import is_tracing
from .rod import Magnet, Rod, SquareSection
from .scene import G_EARTH, Scene, dipole_moment
from .scenes_cosserat import BR_N42, BR_N45, NDFEB, PMC770

__all__ = ["BUILDERS", "MagnetBlockRod", "modal_damping", "on_mesh", "magnetic_rod", "magnetic_rod_heldout", "magnetic_rod_scene", "printed_currents",
           "heldout_currents", "eMNS", "MAGNET_ELEMENTS", "BASE_ROTATION", "FIELD_POINT", "magnetic_rod_planar",
           "magnetic_rod_planar_heldout", "planar_field_basis", "planar_printed_currents", "planar_heldout_currents",
           "PLANAR_BASE", "PLANAR_BASE_ROTATION", "PLANAR_FIELD_POINT", "PlanarFieldCurrents"]

_EDGE, _BODY, _MAG, _NB = 2e-3, 22e-3, 3e-3, 4
MAGNET_ELEMENTS = (_NB, 2 * _NB + 1)  # element index of the proximal and the distal block
RIGID_FACTOR, INERTIA_SCALE, ZETA, DT, DURATION = 20.0, 16.0, 0.25, 8e-5, 24.0
BASE_ROTATION = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))  # half turn about x: E3 -> -z
FIELD_POINT = (0.0, 0.0, -0.036)
_PRINTED_B, _PRINTED_DIRS = 5e-3, ((1, 0), (1, 1), (0, 1), (-1, 0), (-1, -1), (0, -1), (1, -1), (1, 0), None)


@dataclass(frozen=True)
class MagnetBlockRod(Rod):
    """A :class:`~physics.rod.Rod` whose ``rigid_elements`` have ``rigid_factor`` times the bending and
    torsion stiffness (C2): embedded magnet blocks."""

    rigid_elements: tuple[int, ...] = ()
    rigid_factor: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        if not (math.isfinite(self.rigid_factor) and self.rigid_factor >= 1.0):
            raise ValueError(f"MagnetBlockRod.rigid_factor must be >= 1, got {self.rigid_factor!r}")
        # whole element indices, kept as a tuple: 1.5 stiffened element 1 silently and a list left the rod unhashable
        elements = tuple(check_integer("MagnetBlockRod.rigid_elements[i]", e, lo=0) for e in self.rigid_elements)
        if not all(0 <= e < self.N for e in elements):
            raise ValueError(f"MagnetBlockRod.rigid_elements must lie in [0, {self.N}), got {self.rigid_elements}")
        object.__setattr__(self, "rigid_elements", elements)

    def params(self, dtype: torch.dtype = torch.float64, device=None):
        p = super().params(torch.float64)
        C2 = p.C2.clone()
        C2[list(self.rigid_elements)] *= self.rigid_factor
        return p._replace(C2=C2).to(dtype=dtype, device=device)


def _block(s: float, Br: float, name: str) -> Magnet:
    vol = _EDGE * _EDGE * _MAG
    mass = (NDFEB.density - PMC770.density) * vol
    i_perp, i_ax = mass * (_EDGE**2 + _MAG**2) / 12, mass * 2 * _EDGE**2 / 12
    return Magnet(s=s, mass=mass, moment=(0.0, 0.0, dipole_moment(Br, vol)),
                  inertia=(INERTIA_SCALE * i_perp, INERTIA_SCALE * i_perp, INERTIA_SCALE * i_ax), name=name)


def _rod(damping: float = 0.0, rot_damping: float = 0.0, per_part: int = _NB) -> MagnetBlockRod:
    lens = (_BODY / per_part,) * per_part + (_MAG,) + (_BODY / per_part,) * per_part + (_MAG,)
    mags = (_block(_BODY + _MAG / 2, BR_N42, "proximal N42"), _block(2 * _BODY + 1.5 * _MAG, BR_N45, "distal N45"))
    return MagnetBlockRod(2 * (_BODY + _MAG), SquareSection(_EDGE), PMC770, element_lengths=lens, magnets=mags,
                          rotational_inertia_scale=INERTIA_SCALE, damping=damping, rotational_damping=rot_damping,
                          rigid_elements=(per_part, 2 * per_part + 1), rigid_factor=RIGID_FACTOR)


# viscous damping per unit length (N s/m^2, N m s/m), chosen for the modal damping ratios of
# :func:`modal_damping` (a test recomputes them): 25 % in the first bending mode, 48 % in the first
# torsion mode, 8 % in the second bending mode
DAMPING, ROT_DAMPING = 0.107, 1.28e-5


def modal_damping(rod_: Rod, n_modes: int = 6) -> list[tuple[float, float]]:
    """(frequency Hz, damping ratio) of the lowest clamped-free modes: ``phi^T C phi / (2 omega phi^T M phi)``
    with the undamped mode shapes ``phi`` and the rod's viscous coefficients ``C``."""
    import numpy as np
    import scipy.linalg

    from .modal import stiffness_and_mass
    n_modes = check_integer("modal_damping: n_modes", n_modes)
    if n_modes > 6 * rod_.N:  # scipy's eigh: "Requested eigenvalue indices are not valid"; 2.5 gave 2 modes
        raise ValueError(f"modal_damping: n_modes={n_modes} exceeds the {6 * rod_.N} clamped-free modes of this "
                         f"{rod_.N}-element rod")
    K, mass = stiffness_and_mass(rod_)
    keep = np.arange(6, 6 * rod_.n_nodes)
    K, M = K.toarray()[keep][:, keep], mass[keep]
    w2, V = scipy.linalg.eigh(K, np.diag(M), subset_by_index=[0, n_modes - 1])
    prm = rod_.params()
    c = torch.cat((prm.damping, prm.rot_damping), -1).reshape(-1).numpy()[keep]
    w = np.sqrt(w2)
    z = (V * c[:, None] * V).sum(0) / (2 * w * (V * M[:, None] * V).sum(0))
    return [(float(a / (2 * math.pi)), float(b)) for a, b in zip(w, z)]


def rod(per_part: int = _NB) -> MagnetBlockRod:
    """The scene's rod; ``per_part``: elements in each PMC part (the printed 4; a magnet block is always one element)."""
    return _rod(DAMPING, ROT_DAMPING, check_integer("per_part", per_part))


_EMNS = None


def eMNS():
    """The six-coil eMNS of the scene (built once)."""
    global _EMNS
    if _EMNS is None:
        _EMNS = six_coil_emns()
    return _EMNS


def printed_currents() -> MinJerkCurrents:
    """The printed profile (module docstring)."""
    e = eMNS()
    pt = torch.tensor([FIELD_POINT], dtype=torch.float64)
    targets = []
    for d in _PRINTED_DIRS:
        if d is None:
            targets.append(torch.zeros(1, 3, dtype=torch.float64))
        else:
            v = torch.tensor([d[0], d[1], 0.0], dtype=torch.float64)
            targets.append(_PRINTED_B * v / v.norm())
    field = torch.stack([t.reshape(1, 3) for t in targets])
    I = e.allocate(pt.expand(len(targets), 1, 3), field=field).currents
    setpoints = torch.cat([torch.zeros(1, e.n_coils, dtype=torch.float64), I])
    n = setpoints.shape[0]
    return MinJerkCurrents(setpoints, moves=(1.5,) * (n - 1), holds=(0.5,) + (1.0,) * (n - 2) + (2.0,))


def heldout_currents(seed: int = 2024, peak: float = 4.0) -> SinusoidCurrents:
    """Sums of three sinusoids per coil (0.06-0.25 Hz, random phases), scaled to ``peak`` A at most."""
    g = torch.Generator().manual_seed(seed)
    C = eMNS().n_coils
    freqs = 0.06 + 0.19 * torch.rand(3, generator=g, dtype=torch.float64)
    amp = torch.rand(3, C, generator=g, dtype=torch.float64) + 0.2
    amp = amp * peak / amp.sum(0).max()
    phases = 2 * math.pi * torch.rand(3, C, generator=g, dtype=torch.float64)
    return SinusoidCurrents(amp, freqs, phases, ramp=2.0)


_EQ: dict = {}


def _at_rest(base=(0.0, 0.0, 0.0), rotation=BASE_ROTATION):
    """Initial shape: clamped at ``base`` with the base frame ``rotation``, at rest under gravity (static
    equilibrium from the straight rod, zero current)."""
    def initial(rod_: Rod) -> dict:
        key = (rod_, tuple(base), tuple(map(tuple, rotation)))
        if key not in _EQ:
            from .relax import static_equilibrium

            Rb = torch.tensor(rotation, dtype=torch.float64)
            p0 = torch.tensor(base, dtype=torch.float64) + rod_.arclength[:, None] * Rb[:, 2]
            R0 = Rb.expand(rod_.n_nodes, 3, 3).clone()
            _EQ[key] = static_equilibrium(rod_, p0, R0, gravity=(0.0, 0.0, -G_EARTH))
        p, R = _EQ[key]
        return {"p": p.clone(), "R": R.clone()}
    return initial


_hanging = _at_rest()  # hanging straight down from the origin


def magnetic_rod_scene(name: str, currents, title: str, profile: str, duration: float = DURATION,
                       initial=_hanging, base: str = "clamped at the origin hanging down (body E3 = -z)",
                       extra: dict | None = None, paragraphs: tuple[int, ...] = (1, 2)) -> Scene:
    """The rod in the eMNS driven by ``currents(t) -> (C,)`` or ``(V, C)`` A; its description is the module
    docstring's ``paragraphs`` (the planar set-up adds its own) and ``profile``."""
    r = rod()
    return Scene(
        name=name, title=title,
        description=" ".join(__doc__.split("\n\n")[i].strip() for i in paragraphs).replace("\n", " ") + " " + profile,
        rod=r, bc="clamped-free", dt=DT, duration=duration, gravity=(0.0, 0.0, -G_EARTH),
        loads=Loads(field=CoilField(eMNS(), currents)), initial=initial,
        nodes_of_interest=(10, 5), node_labels=("tip (distal magnet, distal end)", "node 6 (proximal magnet, distal end)"),
        thesis={"body": {"E": 2.5e6, "density": 1000.0, "nu": 0.5}, "magnets": ("N42 proximal", "N45 distal"),
                "n_coils": 6, "experiment_duration_s": 340.0, "experiment_samples": 669, "bandwidth_hz": (8.33, 50.0),
                "orientation_errors_deg": {  # Table II.1: (max, mean) about x, y, z
                    "distal": {"rnn": ((1.27, 0.23), (4.69, 1.27), (0.60, 0.10)),
                               "cosserat": ((3.56, 0.82), (10.55, 5.03), (4.02, 2.22))},
                    "proximal": {"rnn": ((1.13, 0.31), (3.30, 0.89), (3.93, 0.31)),
                                 "cosserat": ((1.55, 0.36), (7.22, 3.51), (3.29, 1.99))}}},
        chosen={"elements": r.lengths, "magnet_elements": MAGNET_ELEMENTS, "rigid_factor": RIGID_FACTOR,
                "rotational_inertia_scale": INERTIA_SCALE, "damping_ratio_mode1": ZETA, "damping_ratio_torsion": 0.48,
                "damping": r.damping,
                "rotational_damping": r.rotational_damping, "first_bending_hz": 4.148,
                "magnet_masses": tuple(m.mass for m in r.magnets), "moments": tuple(m.moment[2] for m in r.magnets),
                "base": base, "field_point": FIELD_POINT, "currents": profile, "field_cache_tol_m": 2e-4,
                **(extra or {})})


def on_mesh(scene: Scene, per_part: int) -> Scene:
    """``scene`` (one of this module's) with ``per_part`` elements in each PMC part (:func:`rod`): the same loads,
    clamp and damping per unit length; its headline nodes the tip and the proximal block's distal end again."""
    r = rod(per_part)
    return replace(scene, rod=r, nodes_of_interest=(r.n_nodes - 1, r.rigid_elements[0] + 1),
                   chosen={**scene.chosen, "elements": r.lengths, "magnet_elements": r.rigid_elements})


def magnetic_rod() -> Scene:
    return magnetic_rod_scene(
        "magnetic_rod", printed_currents(),
        "Paper II magnetic rod: two-magnet PMC rod swung by a six-coil eMNS (set-point moves)",
        "Printed currents: minimum-jerk set-point moves to 5 mT fields along +x, +x+y, +y, -x, -x-y, -y, "
        "+x-y, +x and back to zero (1.5 s moves, 1 s holds).")


def magnetic_rod_heldout() -> Scene:
    return magnetic_rod_scene(
        "magnetic_rod_heldout", heldout_currents(),
        "Paper II magnetic rod, held-out: currents as sums of slow sinusoids (never trained on)",
        "Held-out currents: per coil a sum of three sinusoids (0.06-0.25 Hz, seed 2024) faded in over 2 s, "
        "at most 4 A.")


# ------------------------------------------------------------------ the planar set-up of the experiment
# The thesis's experiment (II.5.2): the rod suspended horizontally along x, steered in a plane, magnet
# orientations about y. Here the clamp is at x = -25 mm with body E3 along +x (R_y(90 deg): body E1 along
# -z), so that the straight rod would span the workspace's centre; gravity bends it in the x-z plane
# (the tip sags 17 mm, 28 deg at rest). The eMNS is mirror-symmetric about the x-z plane and the fields
# are requested in that plane at PLANAR_FIELD_POINT (near the rod's middle), so the minimum-norm currents
# are mirror-symmetric too and the whole field on the plane lies in it: the rod moves in the x-z plane.
PLANAR_BASE = (-0.025, 0.0, 0.0)
PLANAR_BASE_ROTATION = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0))
PLANAR_FIELD_POINT = (0.0, 0.0, -0.008)
_PLANAR_B, _PLANAR_ANGLES = 6e-3, (30, 60, 90, 30, -30, -60, -90, -30)


def planar_field_basis() -> torch.Tensor:
    """(2, C) currents (A) per tesla of field along x and along z at :data:`PLANAR_FIELD_POINT` (the eMNS's
    minimum-norm allocation for the field alone, which is linear in the request below the current limits)."""
    e = eMNS()
    pt = torch.tensor([PLANAR_FIELD_POINT], dtype=torch.float64).expand(2, 1, 3)
    unit = 1e-3 * torch.tensor([[[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]]], dtype=torch.float64)
    return e.allocate(pt, field=unit).currents * 1e3


class PlanarFieldCurrents:
    """Currents for the in-plane field ``B(t) = b(t) (cos a(t), 0, sin a(t))`` at :data:`PLANAR_FIELD_POINT`
    (angle ``a`` from +x towards +z): ``b(t) = r(t) (b0 + b1 sin(2 pi f1 t + p1))``, ``a(t) = a0 sin(2 pi f2 t + p2)
    + a1 sin(2 pi f3 t + p3)`` with the fade-in ``r(t) = min_jerk(t / ramp)``: a field that sweeps and
    breathes and never holds still (tesla, rad, Hz)."""

    def __init__(self, b0: float, b1: float, f1: float, p1: float, a0: float, f2: float, p2: float,
                 a1: float, f3: float, p3: float, ramp: float = 2.0):
        vals = (b0, b1, f1, p1, a0, f2, p2, a1, f3, p3, ramp)
        if not all(math.isfinite(v) for v in vals) or ramp <= 0 or min(f1, f2, f3) <= 0:
            raise ValueError(f"PlanarFieldCurrents: parameters must be finite, frequencies and ramp > 0, got {vals}")
        self.params = vals
        self.basis = planar_field_basis()

    def field(self, t) -> tuple[float, float]:
        b0, b1, f1, p1, a0, f2, p2, a1, f3, p3, ramp = self.params
        t = float(t)
        b = min_jerk(t / ramp) * (b0 + b1 * math.sin(2 * math.pi * f1 * t + p1))
        a = a0 * math.sin(2 * math.pi * f2 * t + p2) + a1 * math.sin(2 * math.pi * f3 * t + p3)
        return b * math.cos(a), b * math.sin(a)

    def __call__(self, t) -> torch.Tensor:
        if is_tracing():  # traced (LGVI.compiled_rollout): ``t`` a 0-d tensor
            b0, b1, f1, p1, a0, f2, p2, a1, f3, p3, ramp = self.params
            b = min_jerk(t / ramp) * (b0 + b1 * torch.sin(2 * math.pi * f1 * t + p1))
            a = a0 * torch.sin(2 * math.pi * f2 * t + p2) + a1 * torch.sin(2 * math.pi * f3 * t + p3)
            return (b * torch.cos(a)) * self.basis[0].to(t) + (b * torch.sin(a)) * self.basis[1].to(t)
        bx, bz = self.field(t)
        return bx * self.basis[0] + bz * self.basis[1]


def planar_setpoints(fields) -> torch.Tensor:
    """(n, C) currents for in-plane fields ``fields`` (n, 2) = (B_x, B_z) in tesla."""
    return torch.as_tensor(fields, dtype=torch.float64) @ planar_field_basis()


def planar_printed_currents() -> MinJerkCurrents:
    """Minimum-jerk moves (1.5 s, 1 s holds) through 6 mT fields in the x-z plane at 30, 60, 90, 30, -30,
    -60, -90, -30 deg from +x (towards +z) and back to zero."""
    a = torch.tensor(_PLANAR_ANGLES, dtype=torch.float64) * (math.pi / 180)
    fields = torch.cat([torch.zeros(1, 2, dtype=torch.float64),
                        _PLANAR_B * torch.stack([a.cos(), a.sin()], -1), torch.zeros(1, 2, dtype=torch.float64)])
    n = fields.shape[0]
    return MinJerkCurrents(planar_setpoints(fields), moves=(1.5,) * (n - 1),
                           holds=(0.5,) + (1.0,) * (n - 2) + (2.0,))


def planar_heldout_currents() -> PlanarFieldCurrents:
    """A field of 5 +- 1.5 mT sweeping through +-80 deg about +x (two slow sinusoids, 0.07 and 0.19 Hz)."""
    return PlanarFieldCurrents(5e-3, 1.5e-3, 0.11, 0.3, math.radians(55), 0.07, 0.0, math.radians(25), 0.19, 1.0)


def _planar_scene(name: str, currents, title: str, profile: str) -> Scene:
    base = "clamped at (-25, 0, 0) mm, horizontal along +x (body E3 = +x, E1 = -z), sagging in the x-z plane"
    return magnetic_rod_scene(name, currents, title, profile, initial=_at_rest(PLANAR_BASE, PLANAR_BASE_ROTATION),
                              base=base, paragraphs=(1, 2, 4),
                              extra={"field_point": PLANAR_FIELD_POINT, "base_position": PLANAR_BASE,
                                     "base_rotation": PLANAR_BASE_ROTATION, "plane": "x-z"})


def magnetic_rod_planar() -> Scene:
    return _planar_scene(
        "magnetic_rod_planar", planar_printed_currents(),
        "Paper II magnetic rod, planar as in the experiment: horizontal along x, set-point moves",
        "This scene: the planar printed profile.")


def magnetic_rod_planar_heldout() -> Scene:
    return _planar_scene(
        "magnetic_rod_planar_heldout", planar_heldout_currents(),
        "Paper II magnetic rod, planar, held-out: a sweeping in-plane field (never trained on)",
        "This scene: the planar held-out profile.")


BUILDERS = (magnetic_rod, magnetic_rod_heldout, magnetic_rod_planar, magnetic_rod_planar_heldout)
