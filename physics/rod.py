"""Rod specification: geometry, material, embedded magnets, and the derived discrete parameters.

All inputs in SI. The undeformed rod axis is the body E3 axis; cross-section principal axes
are E1 and E2. A rod of ``N`` elements has ``N + 1`` nodes; element lengths may be non-uniform.

Derived quantities follow Paper I (Table I.2): line mass ``M = rho A``, line inertia
``J = rho diag(I1, I2, I1 + I2)``, ``J_d = tr(J)/2 I - J``,
``C1 = diag(k G A, k G A, E A)`` and ``C2 = diag(E I1, E I2, G J_t)``. Node masses and inertias
lump half of each adjacent element (the midpoint rule of (I.5)); a magnet at arclength ``s``
inside element ``[s_a, s_b]`` adds its mass to both nodes with the linear weights
``(1 - xi, xi)``, ``xi = (s - s_a)/l`` (Remark I.3.1 is the case ``xi = 1/2``; a tip magnet goes
entirely to the tip node).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import torch
from torch import Tensor

from .checks import as_real as _real, is_int, positive

__all__ = [
    "Material", "CircularSection", "SquareSection", "Magnet", "Rod", "RodParams", "StabilityEstimate",
]

_SQUARE_TORSION = 0.1406  # Saint-Venant torsion constant of a square: J_t = 0.1406 a^4


def finite_vector(name: str, v, n: int = 3) -> tuple[float, ...]:
    """``v`` as a tuple of ``n`` floats; ``ValueError`` naming ``name`` unless they are ``n`` finite numbers."""
    try:
        t = tuple(float(x) for x in v)
    except (TypeError, ValueError):  # a scalar, a string, a (3, 1) array
        raise ValueError(f"{name} must be {n} finite numbers, got {v!r}") from None
    if len(t) != n or not all(math.isfinite(x) for x in t):
        raise ValueError(f"{name} must be {n} finite numbers, got {v!r}")
    return t


@dataclass(frozen=True)
class Material:
    """Linear elastic material. Give the Poisson ratio ``nu`` or the shear modulus ``G``."""

    E: float
    density: float
    nu: float | None = None
    G: float | None = None

    def __post_init__(self):
        positive("Material.E (Young's modulus, Pa)", self.E)
        positive("Material.density (kg/m^3)", self.density)
        if self.nu is None and self.G is None:
            raise ValueError("Material: give the Poisson ratio nu or the shear modulus G")
        if self.nu is not None and not (-1.0 < _real("Material.nu (Poisson ratio)", self.nu) <= 0.5):
            raise ValueError(f"Material.nu (Poisson ratio) must lie in (-1, 0.5], got {self.nu!r}")
        if self.G is not None:
            positive("Material.G (shear modulus, Pa)", self.G)
            if self.nu is not None and not math.isclose(self.G, self.shear_modulus_from_nu, rel_tol=1e-6):
                raise ValueError(
                    f"Material: G={self.G} is inconsistent with E={self.E}, nu={self.nu} "
                    f"(E/(2(1+nu)) = {self.shear_modulus_from_nu})"
                )

    @property
    def shear_modulus_from_nu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def shear_modulus(self) -> float:
        return float(self.G) if self.G is not None else self.shear_modulus_from_nu


@dataclass(frozen=True)
class CircularSection:
    diameter: float

    def __post_init__(self):
        positive("CircularSection.diameter (m)", self.diameter)

    @property
    def area(self) -> float:
        return math.pi * self.diameter**2 / 4

    @property
    def second_moments(self) -> tuple[float, float]:
        i = math.pi * self.diameter**4 / 64
        return i, i

    @property
    def torsion_constant(self) -> float:
        return math.pi * self.diameter**4 / 32

    @property
    def min_radius_of_gyration(self) -> float:
        return self.diameter / 4


@dataclass(frozen=True)
class SquareSection:
    """Square cross-section of edge ``edge``; torsion uses Saint-Venant's ``0.1406 a^4``
    (the thesis's Table I.7 used the polar moment ``a^4/6`` instead, 19 % stiffer in torsion)."""

    edge: float

    def __post_init__(self):
        positive("SquareSection.edge (m)", self.edge)

    @property
    def area(self) -> float:
        return self.edge**2

    @property
    def second_moments(self) -> tuple[float, float]:
        i = self.edge**4 / 12
        return i, i

    @property
    def torsion_constant(self) -> float:
        return _SQUARE_TORSION * self.edge**4

    @property
    def min_radius_of_gyration(self) -> float:
        return self.edge / math.sqrt(12)


@dataclass(frozen=True)
class Magnet:
    """A rigid permanent magnet embedded at arclength ``s`` (m from the base node).

    ``moment`` is the dipole moment in the body frame of the cross-section (A m^2);
    ``inertia`` optional principal rotational inertia in the body frame (kg m^2).
    """

    s: float
    mass: float
    moment: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""

    def __post_init__(self):
        if not math.isfinite(_real("Magnet.s (arclength, m)", self.s)) or self.s < 0:
            raise ValueError(f"Magnet.s (arclength, m) must be finite and >= 0, got {self.s!r}")
        if not math.isfinite(_real("Magnet.mass (kg)", self.mass)) or self.mass < 0:
            raise ValueError(f"Magnet.mass (kg) must be finite and >= 0, got {self.mass!r}")
        for nm in ("moment", "inertia"):  # kept as float tuples: a list or tensor left the rod unhashable/unusable
            object.__setattr__(self, nm, finite_vector(f"Magnet.{nm}", getattr(self, nm)))
        if any(x < 0 for x in self.inertia):
            raise ValueError(f"Magnet.inertia must be non-negative, got {self.inertia!r}")


class RodParams(NamedTuple):
    """Tensors the integrator uses (leading batch dims allowed on every field).

    l (..., N) element lengths; C1, C2 (..., N, 3) diagonal stiffnesses; kappa0 (..., N, 3)
    intrinsic curvature; mass (..., n); inertia (..., n, 3) principal node inertia J;
    damping (..., n, 3) translational viscous coefficient (N s/m); rot_damping (..., n, 3)
    (N m s); magnet_elem (K,) element index, magnet_xi (K,), magnet_moment (..., K, 3) body frame.
    """

    l: Tensor
    C1: Tensor
    C2: Tensor
    kappa0: Tensor
    mass: Tensor
    inertia: Tensor
    damping: Tensor
    rot_damping: Tensor
    magnet_elem: Tensor
    magnet_xi: Tensor
    magnet_moment: Tensor

    @property
    def n_nodes(self) -> int:
        return self.mass.shape[-1]

    @property
    def inertia_d(self) -> Tensor:
        """Non-standard inertia J_d = tr(J)/2 I - J (diagonal)."""
        return self.inertia.sum(-1, keepdim=True) / 2 - self.inertia

    def to(self, dtype=None, device=None) -> "RodParams":
        return RodParams(*(t.to(device=device, dtype=dtype) if t.is_floating_point() else t.to(device=device)
                           for t in self))


class StabilityEstimate(NamedTuple):
    """Largest stable time steps (s). ``dt_max`` is ``2/omega_max`` of the linearised discrete
    model (exact for small motions of the explicit update); the others are closed-form
    per-mechanism estimates for a lumped chain with the shortest element."""

    dt_max: float
    dt_axial: float
    dt_shear: float
    dt_bending: float
    dt_torsion: float
    dt_shear_rotation: float
    omega_max: float

    @property
    def limiting(self) -> str:
        named = {k: getattr(self, k) for k in ("dt_axial", "dt_shear", "dt_bending", "dt_torsion",
                                               "dt_shear_rotation")}
        return min(named, key=named.get)[3:]


@dataclass(frozen=True)
class Rod:
    """Geometry, material, magnets and damping of one rod.

    Give ``n_elements`` (uniform) or ``element_lengths`` (summing to ``length``).
    ``shear_coefficient`` is the Timoshenko k in C1 (1 as in the thesis's tables).
    ``damping`` (N s/m^2) and ``rotational_damping`` (N m s/m) are viscous coefficients per unit
    length. ``modulus_scale`` multiplies E and G (the frequency correction gamma_corr, see
    :meth:`frequency_corrected`). ``rotational_inertia_scale`` multiplies the rotational inertia
    (mass scaling of the stiff shear-rotation mode; 1 = physical).
    """

    length: float
    section: CircularSection | SquareSection
    material: Material
    n_elements: int | None = None
    element_lengths: tuple[float, ...] | None = None
    magnets: tuple[Magnet, ...] = field(default_factory=tuple)
    shear_coefficient: float = 1.0
    damping: float = 0.0
    rotational_damping: float = 0.0
    modulus_scale: float = 1.0
    rotational_inertia_scale: float = 1.0
    intrinsic_curvature: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        positive("Rod.length (m)", self.length)
        if not isinstance(self.section, (CircularSection, SquareSection)):
            raise TypeError(f"Rod.section must be CircularSection or SquareSection, got {type(self.section)}")
        if not isinstance(self.material, Material):
            raise TypeError(f"Rod.material must be a Material, got {type(self.material)}")
        if self.element_lengths is None:
            if not is_int(self.n_elements) or self.n_elements < 1:
                raise ValueError(f"Rod.n_elements must be an integer >= 1, got {self.n_elements!r}")
        else:
            ls = tuple(float(x) for x in self.element_lengths)
            if len(ls) < 1 or not all(math.isfinite(x) and x > 0 for x in ls):
                raise ValueError("Rod.element_lengths must be finite positive numbers")
            if not math.isclose(sum(ls), self.length, rel_tol=1e-9):
                raise ValueError(f"Rod.element_lengths sum to {sum(ls)}, not Rod.length={self.length}")
            if self.n_elements is not None and self.n_elements != len(ls):
                raise ValueError("Rod.n_elements disagrees with len(Rod.element_lengths)")
            object.__setattr__(self, "element_lengths", ls)
        object.__setattr__(self, "intrinsic_curvature", finite_vector("Rod.intrinsic_curvature (1/m)",
                                                                      self.intrinsic_curvature))
        object.__setattr__(self, "magnets", tuple(self.magnets))
        for m in self.magnets:
            if not isinstance(m, Magnet):
                raise TypeError(f"Rod.magnets must be Magnet instances, got {type(m)}")
            if m.s > self.length * (1 + 1e-12):
                raise ValueError(f"Magnet at s={m.s} m lies outside the rod (length {self.length} m)")
        positive("Rod.shear_coefficient", self.shear_coefficient)
        positive("Rod.modulus_scale", self.modulus_scale)
        positive("Rod.rotational_inertia_scale", self.rotational_inertia_scale)
        for nm in ("damping", "rotational_damping"):
            v = getattr(self, nm)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"Rod.{nm} must be finite and >= 0, got {v!r}")

    # ------------------------------------------------------------------ geometry
    @property
    def lengths(self) -> tuple[float, ...]:
        if self.element_lengths is not None:
            return self.element_lengths
        return (self.length / self.n_elements,) * self.n_elements

    @property
    def N(self) -> int:
        return len(self.lengths)

    @property
    def n_nodes(self) -> int:
        return self.N + 1

    @property
    def arclength(self) -> Tensor:
        """Node arclengths (n,) in float64."""
        return torch.cat((torch.zeros(1, dtype=torch.float64),
                          torch.tensor(self.lengths, dtype=torch.float64).cumsum(0)))

    # ------------------------------------------------------------------ line quantities
    @property
    def line_mass(self) -> float:
        """M = rho A (kg/m)."""
        return self.material.density * self.section.area

    @property
    def line_inertia(self) -> tuple[float, float, float]:
        """J = rho diag(I1, I2, I1 + I2) (kg m), scaled by ``rotational_inertia_scale``."""
        i1, i2 = self.section.second_moments
        r = self.material.density * self.rotational_inertia_scale
        return (r * i1, r * i2, r * (i1 + i2))

    @property
    def line_inertia_d(self) -> tuple[float, float, float]:
        J = self.line_inertia
        t = sum(J) / 2
        return tuple(t - j for j in J)

    @property
    def C1(self) -> tuple[float, float, float]:
        E = self.material.E * self.modulus_scale
        G = self.material.shear_modulus * self.modulus_scale
        A = self.section.area
        k = self.shear_coefficient
        return (k * G * A, k * G * A, E * A)

    @property
    def C2(self) -> tuple[float, float, float]:
        E = self.material.E * self.modulus_scale
        G = self.material.shear_modulus * self.modulus_scale
        i1, i2 = self.section.second_moments
        return (E * i1, E * i2, G * self.section.torsion_constant)

    def magnet_weights(self) -> list[tuple[int, float]]:
        """(element index, xi in [0, 1]) of each magnet."""
        s = self.arclength.tolist()
        out = []
        for m in self.magnets:
            e = min(max(0, next((i for i in range(self.N) if m.s <= s[i + 1] + 1e-15), self.N - 1)), self.N - 1)
            xi = min(max((m.s - s[e]) / self.lengths[e], 0.0), 1.0)
            out.append((e, xi))
        return out

    def node_masses(self) -> Tensor:
        """Lumped node masses (n,) in kg, float64."""
        m = self.line_mass * self.node_weights()
        for (e, xi), mag in zip(self.magnet_weights(), self.magnets):
            m[e] += (1 - xi) * mag.mass
            m[e + 1] += xi * mag.mass
        return m

    def node_weights(self) -> Tensor:
        """Length lumped at each node: half of each adjacent element (n,), float64."""
        l = torch.tensor(self.lengths, dtype=torch.float64)
        w = torch.zeros(self.n_nodes, dtype=torch.float64)
        w[:-1] += l / 2
        w[1:] += l / 2
        return w

    def params(self, dtype: torch.dtype = torch.float64, device=None) -> RodParams:
        """The discrete parameters as tensors of ``dtype`` on ``device``."""
        n, N = self.n_nodes, self.N
        w = self.node_weights()
        J = torch.tensor(self.line_inertia, dtype=torch.float64)
        inertia = w[:, None] * J
        for (e, xi), mag in zip(self.magnet_weights(), self.magnets):
            Jm = torch.tensor(mag.inertia, dtype=torch.float64)
            inertia[e] += (1 - xi) * Jm
            inertia[e + 1] += xi * Jm
        K = len(self.magnets)
        mw = self.magnet_weights()
        p = RodParams(
            l=torch.tensor(self.lengths, dtype=torch.float64),
            C1=torch.tensor(self.C1, dtype=torch.float64).expand(N, 3).clone(),
            C2=torch.tensor(self.C2, dtype=torch.float64).expand(N, 3).clone(),
            kappa0=torch.tensor(self.intrinsic_curvature, dtype=torch.float64).expand(N, 3).clone(),
            mass=self.node_masses(),
            inertia=inertia,
            damping=(self.damping * w)[:, None].expand(n, 3).clone(),
            rot_damping=(self.rotational_damping * w)[:, None].expand(n, 3).clone(),
            magnet_elem=torch.tensor([e for e, _ in mw], dtype=torch.long),
            magnet_xi=torch.tensor([x for _, x in mw], dtype=torch.float64),
            magnet_moment=torch.tensor([m.moment for m in self.magnets], dtype=torch.float64).reshape(K, 3),
        )
        return p.to(dtype=dtype, device=device)

    # ------------------------------------------------------------------ derived analysis
    def stable_time_step(self) -> StabilityEstimate:
        """Largest stable explicit time step; see :class:`StabilityEstimate`."""
        from .modal import max_frequency

        rho = self.material.density
        E = self.material.E * self.modulus_scale
        G = self.material.shear_modulus * self.modulus_scale * self.shear_coefficient
        lmin = min(self.lengths)
        i1, i2 = self.section.second_moments
        A = self.section.area
        s = self.rotational_inertia_scale
        dt_axial = lmin * math.sqrt(rho / E)
        dt_shear = lmin * math.sqrt(rho / G)
        dt_bending = lmin * math.sqrt(rho * s / E)
        dt_torsion = lmin * math.sqrt(rho * s * (i1 + i2) / (G / self.shear_coefficient * self.section.torsion_constant))
        # the row-sum (Gershgorin) bound of the rotational stiffness per inertia, shear and bending (within 2 % of
        # the exact dt_max on uniform meshes; a node rotating alone would give half of it, not a safe bound)
        dt_shear_rotation = 2.0 / math.sqrt(G * A / (rho * s * min(i1, i2)) + 4 * E / (rho * s * lmin**2))
        w = max_frequency(self)
        return StabilityEstimate(2.0 / w, dt_axial, dt_shear, dt_bending, dt_torsion, dt_shear_rotation, w)

    def natural_frequencies(self, bc: str = "clamped-free", n_modes: int = 6) -> Tensor:
        """Lowest angular frequencies (rad/s) of the linearised discrete model about the straight
        configuration, for ``bc`` in {'clamped-free', 'clamped-clamped', 'free-free'}."""
        from .modal import frequencies

        return frequencies(self, bc=bc, n_modes=n_modes)

    def euler_bernoulli_first_frequency(self) -> float:
        """First clamped-free bending frequency 1.8751^2 sqrt(E I / (rho A L^4)) (rad/s) of the
        physical modulus (``modulus_scale`` and magnet masses ignored)."""
        E = self.material.E
        I = min(self.section.second_moments)
        return 1.8751040687**2 * math.sqrt(E * I / (self.line_mass * self.length**4))

    def frequency_correction(self, bc: str = "clamped-free") -> float:
        """gamma_corr = (omega_EB / omega_N)^2: the modulus factor that makes the discrete
        model's first bending frequency equal the continuum one (Paper I, I.5). A correction of the mesh alone: both
        frequencies are the rod's without its magnets (their mass is physics, not discretisation error)."""
        if bc != "clamped-free":
            raise ValueError("frequency_correction: only bc='clamped-free' has a closed-form reference")
        wN = float(replace(self, magnets=()).natural_frequencies(bc, n_modes=1)[0])
        return (self.euler_bernoulli_first_frequency() / wN) ** 2

    def frequency_corrected(self, bc: str = "clamped-free") -> "Rod":
        return replace(self, modulus_scale=self.modulus_scale * self.frequency_correction(bc))
