"""Analytic reference problems shared by the tests (SI units)."""
from __future__ import annotations

import math

from physics import CircularSection, Material, Rod

G_EARTH = 9.81


def steel_like_rod(n_elements: int = 20, length: float = 0.2, diameter: float = 0.01, **kw) -> Rod:
    """A slender circular rod (L/r = 40 by default) of a soft polymer: fast to simulate."""
    return Rod(length=length, section=CircularSection(diameter),
               material=Material(E=kw.pop("E", 2.0e6), density=kw.pop("density", 1000.0), nu=0.3),
               n_elements=n_elements, **kw)


def aluminium_rod(n_elements: int = 10, **kw) -> Rod:
    """The 2 mm AlSi5 rod of Paper I (E 75 GPa, rho 2690, nu 0.33, L 200 mm)."""
    return Rod(length=0.2, section=CircularSection(2e-3), material=Material(E=75e9, density=2690.0, nu=0.33),
               n_elements=n_elements, **kw)


def pdms_rod(n_elements: int = 10, **kw) -> Rod:
    """The 4 mm PDMS rod of Paper I (E 365.12 kPa, rho 1101, nu 0.5, L 60.55 mm)."""
    return Rod(length=0.06055, section=CircularSection(4e-3), material=Material(E=365.12e3, density=1101.0, nu=0.5),
               n_elements=n_elements, **kw)


def EI(rod: Rod) -> float:
    return rod.material.E * rod.section.second_moments[0]


def cantilever_uniform_load_tip(rod: Rod, q: float) -> float:
    """Tip deflection q L^4 / (8 E I) of a cantilever under a uniform line load q (N/m)."""
    return q * rod.length**4 / (8 * EI(rod))


def cantilever_tip_force(rod: Rod, P: float) -> float:
    return P * rod.length**3 / (3 * EI(rod))


def cantilever_tip_moment(rod: Rod, M: float) -> float:
    return M * rod.length**2 / (2 * EI(rod))


def clamped_clamped_mid(rod: Rod, q: float) -> float:
    """Midspan deflection q L^4 / (384 E I) of a clamped-clamped beam."""
    return q * rod.length**4 / (384 * EI(rod))


def eb_first_frequency(rod: Rod) -> float:
    """1.8751^2 sqrt(E I / (rho A L^4)) in rad/s."""
    return 1.8751040687**2 * math.sqrt(EI(rod) / (rod.line_mass * rod.length**4))
