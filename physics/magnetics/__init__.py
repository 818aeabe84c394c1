"""Magnetic actuation: point dipoles, permanent magnets as dipole grids, coils and electromagnetic
navigation systems. Batched, differentiable torch; SI units (T, A m^2, A, m).

Every field model is a :class:`FieldModel`: ``field(points)``, ``field_and_gradient(points)``,
``force_torque(points, moments)``, and it plugs into the rod solvers' magnet hook as is.
"""
from .base import FieldModel, Superposition, TimeVarying, UniformField
from .coils import (CircularLoop, Coil, HelmholtzPair, NestedHelmholtz, RotatingField, helmholtz_centre_field,
                    loop_field_per_amp, loop_on_axis_field, paper1_rotating_field)
from .dipole import (MU0, dipole_dipole_force, dipole_field, dipole_field_gradient, dipole_force, dipole_torque,
                     five_to_gradient, force_from_gradient, force_map, gradient_to_five, moment_from_remanence)
from .elliptic import agm_iterations, ellipe, ellipk
from .emns import EMNS, MAX_ENUMERATED_COILS, Allocation, allocate_currents, six_coil_emns
from .field_table import CoilFieldTable
from .magnets import CuboidMagnet, CylinderMagnet, MagnetField, SphereMagnet
from .sources import DipoleSet

__all__ = [
    "FieldModel", "Superposition", "TimeVarying", "UniformField",
    "CircularLoop", "Coil", "HelmholtzPair", "NestedHelmholtz", "RotatingField", "helmholtz_centre_field",
    "loop_field_per_amp", "loop_on_axis_field", "paper1_rotating_field",
    "MU0", "dipole_dipole_force", "dipole_field", "dipole_field_gradient", "dipole_force", "dipole_torque",
    "five_to_gradient", "force_from_gradient", "force_map", "gradient_to_five", "moment_from_remanence",
    "agm_iterations", "ellipe", "ellipk",
    "EMNS", "MAX_ENUMERATED_COILS", "Allocation", "allocate_currents", "six_coil_emns", "CoilFieldTable",
    "CuboidMagnet", "CylinderMagnet", "MagnetField", "SphereMagnet", "DipoleSet",
]
