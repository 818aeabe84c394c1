"""Named scenes: the six experiments of Paper I (Table I.8) and Simulations I-III of Paper II.

``SCENES`` maps each name to a :class:`~physics.scene.Scene`; :func:`get_scene` looks one up.
Every scene is in SI; its ``description`` says what was chosen where the thesis is silent and
its ``thesis`` dict keeps the printed parameters (Tables I.3-I.7, converted to SI) and errors
(Table I.8) for comparison. Paper II scenes live in :mod:`physics.scenes_paper2` (Simulations I-III)
and :mod:`physics.scenes_magnetic_rod` (the two-magnet rod in the six-coil eMNS).

Frames (Paper I). The world frame is the thesis's (E1, E2, E3) with the undeformed rod along
+E3 from a clamp at the origin (identity base frame). The aluminium rods hang: gravity acts along
the rod axis (+E3 points down), as the text says ("gravity in the E3-axis direction"; the tables'
``F^c = [0, 0, Mg]`` with ``E3 = [1, 0, 0]`` would instead put it across the rod). The PDMS rods
are horizontal with gravity along -E2 (the text: "gravity acting along E2") and move in the
E2E3-plane. Moduli follow reference/README.md: PDMS 365.12 kPa (the printed "MPa" is a typo) and
3.6512 MPa (ten times that) for the square rod of Table I.7, which reproduce its C1, C2.

Initial shapes. A released bend is the tip-load bending shape (:func:`physics.shapes.bent_cantilever`)
with nodes placed free of discrete shear and axial strain, so only bending energy is stored; the
driven magnetic scenes start at rest in static equilibrium under gravity and the field at t = 0
(:func:`physics.relax.static_equilibrium`).

Damping. The thesis captures dissipation online with the estimation filters (I.17)-(I.21). The
free-vibration scenes here are undamped (their LGVI energy is conserved); the two driven,
quasi-static magnetic scenes get a light viscous damping of 5 % of critical in the first mode
(``c = 2 zeta omega_1 m_rod / L``) so that they settle; see each description.
"""
from __future__ import annotations

import math

import torch

from .checks import positive, real
from .loads import Loads, UniformField
from .magnetics.validate import vec3
from .programs import is_tracing
from .rod import CircularSection, Magnet, Material, Rod, SquareSection
from .scene import G_EARTH, Scene, dipole_moment, table_to_si
from .shapes import bent_cantilever, cantilever_rotation_for_offset
from . import scenes_magnetic_rod, scenes_paper2

__all__ = ["SCENES", "get_scene", "scene_names", "UnknownSceneError", "RotatingField", "SweptField"]

_AL = Material(E=75e9, density=2690.0, nu=0.33)
_PDMS = Material(E=365.12e3, density=1101.0, nu=0.5)
_PDMS_SQUARE = Material(E=3.6512e6, density=1101.0, nu=0.5)
BR_N45 = 1.345  # T, midpoint of the printed 1.32-1.37 (N45 NdFeB)


def _err(max_mm: float, mean_mm: float, percent: float) -> dict:
    return {"max": max_mm * 1e-3, "mean": mean_mm * 1e-3, "max_percent": percent}


def _cylinder_magnet(s: float, mass: float, d: float, h: float, sign: float, name: str) -> Magnet:
    """Axially magnetised cylinder (axis along the rod's E3), moment Br V / mu0, solid inertia."""
    r = d / 2
    m = dipole_moment(BR_N45, math.pi * r * r * h)
    i_perp = mass * (3 * r * r + h * h) / 12
    return Magnet(s=s, mass=mass, moment=(0.0, 0.0, sign * m), inertia=(i_perp, i_perp, mass * r * r / 2), name=name)


def _equilibrium(gravity, field_at_start):
    """Initial-configuration builder: at rest in static equilibrium under gravity and the field at
    t = 0 (found once per rod by :func:`physics.relax.static_equilibrium` and cached)."""
    cache: dict = {}

    def build(rod: Rod) -> dict:
        if rod not in cache:
            from .relax import static_equilibrium

            p0 = torch.zeros(rod.n_nodes, 3, dtype=torch.float64)
            p0[:, 2] = rod.arclength
            R0 = torch.eye(3, dtype=torch.float64).expand(rod.n_nodes, 3, 3).clone()
            cache[rod] = static_equilibrium(rod, p0, R0, gravity=gravity, field=field_at_start)
        p, R = cache[rod]
        return {"p": p.clone(), "R": R.clone()}

    return build


def _deflected(tip_rotation):
    """Initial-configuration builder: the rod bent as by a tip load, at rest."""
    th = tuple(float(x) for x in tip_rotation)

    def build(rod: Rod) -> dict:
        p, R = bent_cantilever(rod.arclength.tolist(), th)
        return {"p": p, "R": R}

    return build


class RotatingField:
    """``B(t) = B_static + B_rot (cos(w t) e_a + sin(w t) e_b)`` (T), ``w = 2 pi f``."""

    def __init__(self, static, amplitude: float, frequency: float, e_a, e_b):
        # checked here: a 2-vector failed in torch at the first step, a NaN gave a NaN field
        self.static = torch.tensor(vec3("RotatingField.static (T)", static), dtype=torch.float64)
        self.amplitude = real("RotatingField.amplitude (T)", amplitude)
        self.frequency = real("RotatingField.frequency (Hz)", frequency)
        self.e_a, self.e_b = (torch.tensor(vec3(f"RotatingField.{k}", v), dtype=torch.float64)
                              for k, v in (("e_a", e_a), ("e_b", e_b)))

    def __call__(self, t) -> torch.Tensor:
        if is_tracing():  # traced (LGVI.compiled_rollout): ``t`` a 0-d tensor
            w = 2 * math.pi * self.frequency * t
            return self.static.to(t) + self.amplitude * (torch.cos(w) * self.e_a.to(t) + torch.sin(w) * self.e_b.to(t))
        w = 2 * math.pi * self.frequency * float(t)  # t: float or 0-d tensor
        return self.static + self.amplitude * (math.cos(w) * self.e_a + math.sin(w) * self.e_b)


class SweptField:
    """Field of magnitude ``b0 -> b1`` (linear over ``period``) whose direction sweeps out and back
    in the (e_a, e_b)-plane: angle ``phi_max sin^2(pi t / period)`` from ``e_a`` towards ``e_b``."""

    def __init__(self, b0: float, b1: float, period: float, phi_max: float, e_a, e_b):
        # checked here: period 0 divided by zero at the first step, a negative one held the field at b0 along e_a
        self.b0, self.b1 = real("SweptField.b0 (T)", b0), real("SweptField.b1 (T)", b1)
        self.period, self.phi_max = positive("SweptField.period (s)", period), real("SweptField.phi_max (rad)", phi_max)
        self.e_a, self.e_b = (torch.tensor(vec3(f"SweptField.{k}", v), dtype=torch.float64)
                              for k, v in (("e_a", e_a), ("e_b", e_b)))

    def __call__(self, t) -> torch.Tensor:
        if is_tracing():  # traced (LGVI.compiled_rollout): ``t`` a 0-d tensor
            x = (t / self.period).clamp(0.0, 1.0)
            phi = self.phi_max * torch.sin(math.pi * x) ** 2
            return (self.b0 + (self.b1 - self.b0) * x) * (torch.cos(phi) * self.e_a.to(t) + torch.sin(phi) * self.e_b.to(t))
        x = min(max(float(t) / self.period, 0.0), 1.0)
        b = self.b0 + (self.b1 - self.b0) * x
        phi = self.phi_max * math.sin(math.pi * x) ** 2
        return b * (math.cos(phi) * self.e_a + math.sin(phi) * self.e_b)


# ---------------------------------------------------------------------------------------- Paper I
def al_inplane() -> Scene:
    scale = 20.0
    rod = Rod(0.2, CircularSection(2e-3), _AL, n_elements=15, rotational_inertia_scale=scale)
    th = math.radians(3.69)
    return Scene(
        name="al_inplane",
        title="Paper I exp. 1: hanging Al rod (d 2 mm, L 200 mm) released from a 3.69 deg in-plane bend",
        description=(
            "Paper I experiment 1: hanging aluminium rod (d 2 mm, L 200 mm, 15 elements) released from an "
            "in-plane tip deflection of 3.69 deg in the E1E3-plane. Gravity acts along the rod (+E3 points "
            "down). Initial shape: the tip-load bending shape (curvature falling linearly to zero at the "
            "tip) with the tip cross-section rotated 3.69 deg about E2 (tip ~8.6 mm along +E1). dt = 1e-6 s "
            "as in Table I.3; it exceeds the physical shear-rotation limit (dt_max 3.1e-7 s), so the "
            "rotational inertia is mass-scaled by 20 (dt/dt_max 0.73); this shifts the first bending "
            "frequency by < 0.03 %. Undamped (the thesis's damping filters are not part of the scene)."),
        rod=rod, bc="clamped-free", dt=1e-6, duration=1.5, gravity=(0.0, 0.0, G_EARTH),
        initial=_deflected((0.0, th, 0.0)), nodes_of_interest=(15,), node_labels=("tip",),
        thesis=table_to_si(
            table="I.3", n_elements=15, M=8.45e-3, J_d=(0.0, 2.11, 2.11), C1=(2.35e14, 0.88e14, 0.88e14),
            C2=(4.42e13, 5.89e13, 5.89e13), F_c=8.29e4, dt=1e-6, duration=1.5, filter_R=1e4, filter_W=0.1,
            initial_tip_rotation_deg=3.69, errors={"tip E1": _err(0.15, 0.05, 2.50)}),
        chosen={"rotational_inertia_scale": scale, "dt_max_physical": 3.09e-7,
                "gravity": "along +E3 (rod hangs)", "initial_tip_rotation_axis": "E2"},
    )


def al_3d() -> Scene:
    scale = 80.0
    rod = Rod(0.2, CircularSection(1e-3), _AL, n_elements=15, rotational_inertia_scale=scale)
    offset = (10e-3, -8e-3)
    th = cantilever_rotation_for_offset(rod.arclength.tolist(), offset)
    return Scene(
        name="al_3d",
        title="Paper I exp. 2: hanging Al rod (d 1 mm, L 200 mm) released from an out-of-plane bend",
        description=(
            "Paper I experiment 2: hanging aluminium rod (d 1 mm, L 200 mm, 15 elements) released from an "
            "out-of-plane tip deflection. The printed tip offsets are used: +10 mm along E1 (theta_E1E3 = "
            "6.52 deg) and -8 mm along E2 (theta_E1E2 = -5.53 deg); the printed angles are not consistent "
            "with those offsets on a 200 mm cantilever (the tip-load shape gives tip rotations of 4.31 and "
            "3.45 deg), so the offsets are kept and the angles recorded. Gravity along the rod (+E3 down). "
            "dt = 1e-6 s as printed with the rotational inertia mass-scaled by 80 (physical dt_max 1.5e-7 "
            "s; dt/dt_max 0.73; bending frequencies change < 0.01 %). Undamped."),
        rod=rod, bc="clamped-free", dt=1e-6, duration=1.5, gravity=(0.0, 0.0, G_EARTH),
        initial=_deflected(th), nodes_of_interest=(15,), node_labels=("tip",),
        thesis=table_to_si(
            table="I.4", n_elements=15, M=2.11e-3, J_d=(0.0, 0.13, 0.13), C1=(5.89e13, 2.21e13, 2.21e13),
            C2=(2.76e12, 3.68e12, 3.68e12), F_c=2.07e4, dt=1e-6, duration=1.5, filter_R=1e4, filter_W=0.1,
            initial_tip_rotation_deg={"E1E2": -5.53, "E1E3": 6.52}, initial_tip_offset={"E2": 8e-3, "E3": 10e-3},
            errors={"tip, both axes": _err(0.15, 0.05, 2.12)}),
        chosen={"rotational_inertia_scale": scale, "dt_max_physical": 1.54e-7, "initial_tip_offset": offset,
                "gravity": "along +E3 (rod hangs)"},
    )


def pdms_inplane() -> Scene:
    rod = Rod(0.0605, CircularSection(5e-3), _PDMS, n_elements=10)
    return Scene(
        name="pdms_inplane",
        title="Paper I exp. 3: horizontal PDMS rod (D 5 mm) released straight under gravity",
        description=(
            "Paper I experiment 3: horizontal PDMS rod (D 5 mm, L 60.5 mm, E 365.12 kPa, 10 elements) "
            "released straight and at rest under gravity along -E2; it sags and oscillates in the "
            "E2E3-plane. dt = 8e-5 s as printed (dt/dt_max 0.34). Undamped."),
        rod=rod, bc="clamped-free", dt=8e-5, duration=1.5, gravity=(0.0, -G_EARTH, 0.0),
        nodes_of_interest=(10,), node_labels=("tip",),
        thesis=table_to_si(
            table="I.5", n_elements=10, M=21.62e-3, J_d=(0.0, 33.78, 33.78), C1=(7.17e9, 2.39e9, 2.39e9),
            C2=(0.75e10, 1.12e10, 1.12e10), F_c=2.12e5, dt=8e-5, duration=1.5, filter_R=1e5, filter_W=0.1,
            E_printed="365.12 MPa (typo for kPa)",
            errors={"tip E2": _err(0.56, 0.05, 4.87), "tip E3": _err(0.28, 0.05, 4.89)}),
        chosen={"gravity": "along -E2"},
    )


def _pdms_tip_magnet_rod(damping: float = 0.0) -> Rod:
    magnet = _cylinder_magnet(0.06055, 9.6e-5, 2e-3, 4e-3, +1.0, "tip")
    return Rod(0.06055, CircularSection(4e-3), _PDMS, n_elements=10, magnets=(magnet,), damping=damping)


_TABLE_I6 = table_to_si(
    table="I.6", n_elements=10, M=13.83e-3, J_d=(0.0, 13.83, 13.83), C1=(4.58e9, 1.53e9, 1.53e9),
    C2=(3.06e9, 4.59e9, 4.59e9), F_c={"nodes 1..N": 1.357e5, "node N+1": 1.36e5}, dt=9e-5, duration=2.0,
    filter_R=1e5, filter_W=0.1, magnet_mass=9.6e-5, magnet_size=(2e-3, 4e-3), Br=(1.32, 1.37),
    magnet_volume=4 * math.pi * 1e-9)


def pdms_tip_magnet() -> Scene:
    rod = _pdms_tip_magnet_rod()
    return Scene(
        name="pdms_tip_magnet",
        title="Paper I exp. 4: PDMS rod with a tip magnet released from a -41.74 deg bend",
        description=(
            "Paper I experiment 4: horizontal PDMS rod (D 4 mm, L 60.55 mm, 10 elements) with an N45 tip "
            "magnet (D 2 mm x 4 mm, 0.096 g, m = Br V / mu0 = 0.0135 A m^2 along the rod, Br 1.345 T), "
            "released from -41.74 deg about E1 (tip raised towards +E2, against gravity along -E2). No "
            "field is applied, so the magnet acts as a lumped mass and inertia at the tip. Initial shape: "
            "tip-load bending shape. dt = 9e-5 s as printed (dt/dt_max 0.48). Undamped."),
        rod=rod, bc="clamped-free", dt=9e-5, duration=2.0, gravity=(0.0, -G_EARTH, 0.0),
        initial=_deflected((math.radians(-41.74), 0.0, 0.0)), nodes_of_interest=(10,), node_labels=("tip",),
        thesis=dict(_TABLE_I6, initial_tip_rotation_deg=-41.74,
                    errors={"tip E2": _err(0.61, 0.14, 3.35), "tip E3": _err(0.55, 0.13, 1.16)}),
        chosen={"Br": BR_N45, "magnet_moment_direction": "+E3 (axial)", "gravity": "along -E2"},
    )


def pdms_circular() -> Scene:
    damping = 0.022  # 5 % of critical in the first mode (omega_1 = 14.4 rad/s)
    rod = _pdms_tip_magnet_rod(damping)
    field = RotatingField(static=(0.0, 7.75e-3, 0.0), amplitude=14.5e-3, frequency=0.5,
                          e_a=(0.0, 1.0, 0.0), e_b=(1.0, 0.0, 0.0))
    return Scene(
        name="pdms_circular",
        title="Paper I exp. 5: tip-magnet PDMS rod driven around a circle by a rotating field",
        description=(
            "Paper I experiment 5: the tip-magnet PDMS rod driven so that its tip circles around the rod "
            "axis, by a uniform field B(t) = 7.75 mT E2 (gravity compensation, opposing gravity along -E2) "
            "+ 14.5 mT (cos(w t) E2 + sin(w t) E1), w = 2 pi x 0.5 Hz. Reading: the rotating field turns "
            "in the plane normal to the rod, i.e. the thesis's 'E2E3-plane' in the frame of its tables, "
            "where the rod axis is [1, 0, 0]; this is what the setup can make (coil pairs along its E1 "
            "and E2 only), what makes a circle (a field rotating in the plane that contains the rod "
            "passes through anti-parallel to the moment and snaps the rod over instead) and why the "
            "experiment needed 3D stereo reconstruction. B_g levels the tip: by linear theory its torque "
            "rotates the tip by 1.37 rad against gravity's 1.47 rad. Chosen: 0.5 Hz (one turn in the 2 s "
            "of Table I.6, below the first bending frequency 2.3 Hz); the rod starts at rest in static "
            "equilibrium under gravity and B(0) = 22.25 mT E2; viscous damping 0.022 N s/m^2 (5 % of "
            "critical in mode 1). dt = 9e-5 s as printed."),
        rod=rod, bc="clamped-free", dt=9e-5, duration=2.0, gravity=(0.0, -G_EARTH, 0.0),
        loads=Loads(field=UniformField(field)), initial=_equilibrium((0.0, -G_EARTH, 0.0), field(0.0)),
        nodes_of_interest=(10,), node_labels=("tip",),
        thesis=dict(_TABLE_I6, B_gravity_compensation=7.75e-3, B_rotating=14.5e-3, B_max_setup=45e-3,
                    rotation_plane_printed="E2E3", errors={"tip, Euclidean": _err(1.20, 0.59, 1.43)}),
        chosen={"rotation_frequency_hz": 0.5, "rotation_plane": "E1E2 (normal to the rod), from +E2 towards +E1",
                "damping": damping, "damping_ratio_mode1": 0.05, "Br": BR_N45,
                "initial_state": "static equilibrium under gravity and B(0)"},
    )


def pdms_square_two_magnets() -> Scene:
    scale, damping, L = 16.0, 0.0070, 0.0855
    mags = (_cylinder_magnet(L - 0.0361, 7.2e-5, 2e-3, 3e-3, -1.0, "middle"),
            _cylinder_magnet(L, 7.2e-5, 2e-3, 3e-3, +1.0, "tip"))
    rod = Rod(L, SquareSection(2e-3), _PDMS_SQUARE, n_elements=10, magnets=mags, damping=damping,
              rotational_inertia_scale=scale)
    field = SweptField(20e-3, 19.85e-3, 7.5, math.pi / 2, e_a=(0.0, 0.0, 1.0), e_b=(0.0, 1.0, 0.0))
    return Scene(
        name="pdms_square_two_magnets",
        title="Paper I exp. 6: square PDMS rod with two magnets bent by a swept field",
        description=(
            "Paper I experiment 6: horizontal square PDMS rod (a 2 mm, L 85.5 mm, E 3.65 MPa, 10 elements) "
            "with two N45 magnets (D 2 mm x 3 mm, 0.072 g, 0.0101 A m^2) at the tip (moment +E3) and 36.1 mm "
            "from the tip (moment -E3: 'different directions', chosen antiparallel), bent into an S in the "
            "E2E3-plane by a uniform field. Chosen profile: |B| falls linearly from 20 to 19.85 mT over "
            "7.5 s while its direction sweeps from +E3 to +E2 and back (angle 90 deg sin^2(pi t/7.5 s)), so "
            "the field starts and ends along the rod. The rod starts at rest in static equilibrium under "
            "gravity (along -E2) and B(0); damping 0.007 N s/m^2 (5 % of critical in mode 1). The "
            "printed dt = 1e-4 s is 2.9x the physical limit (3.5e-5 s), so the rod's rotational inertia "
            "is mass-scaled by 16 (dt/dt_max 0.74). Torsion uses Saint-Venant's 0.1406 a^4 (Table I.7 "
            "used a^4/6). The middle magnet sits inside element 5 (xi 0.78); node 6 is reported for it."),
        rod=rod, bc="clamped-free", dt=1e-4, duration=7.5, gravity=(0.0, -G_EARTH, 0.0),
        loads=Loads(field=UniformField(field)), initial=_equilibrium((0.0, -G_EARTH, 0.0), field(0.0)),
        nodes_of_interest=(10, 6), node_labels=("tip", "node 6 (middle magnet at 5.78 elements)"),
        thesis=table_to_si(
            table="I.7", n_elements=10, M=4.40e-3, J_d=(0.0, 1.47, 1.47), C1=(1.46e10, 0.49e10, 0.49e10),
            C2=(3.25e9, 4.87e9, 4.87e9), F_c={"nodes 1,2,5..N": 4.32e4, "nodes 3,4,N+1": 4.33e4}, dt=1e-4,
            duration=7.5, filter_R=1e5, filter_W=0.1, magnet_mass=7.2e-5, magnet_size=(2e-3, 3e-3),
            middle_magnet_from_tip=36.1e-3, B_initial=20e-3, B_final=19.85e-3,
            errors={"tip E2": _err(1.00, 0.15, 2.24), "tip E3": _err(1.40, 0.33, 5.13),
                    "middle E2": _err(0.47, 0.08, 2.05), "middle E3": _err(0.40, 0.10, 3.68)}),
        chosen={"rotational_inertia_scale": scale, "dt_max_physical": 3.50e-5, "damping": damping,
                "damping_ratio_mode1": 0.05, "magnet_moments": "tip +E3, middle -E3",
                "field_profile": "|B| 20 -> 19.85 mT linear; direction 90 deg sin^2(pi t/T) from +E3 to +E2",
                "Br": BR_N45, "torsion_constant": "0.1406 a^4 (Saint-Venant)",
                "initial_state": "static equilibrium under gravity and B(0)"},
    )


# ---------------------------------------------------------------------------------------- registry
_BUILDERS = (al_inplane, al_3d, pdms_inplane, pdms_tip_magnet, pdms_circular, pdms_square_two_magnets,
             *scenes_paper2.BUILDERS, *scenes_magnetic_rod.BUILDERS)

SCENES: dict[str, Scene] = {s.name: s for s in (b() for b in _BUILDERS)}


class UnknownSceneError(KeyError):
    """An unknown scene name; the message lists the valid names."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def scene_names() -> list[str]:
    return list(SCENES)


def get_scene(name: str) -> Scene:
    """The scene called ``name``; :class:`UnknownSceneError` (a ``KeyError``) listing the valid
    names otherwise."""
    try:
        return SCENES[name]
    except (KeyError, TypeError):
        raise UnknownSceneError(f"unknown scene {name!r}; valid scenes: {', '.join(SCENES)}") from None
