"""Magnetic actuation: point dipoles, permanent magnets as dipole grids, coils and electromagnetic
navigation systems. Batched, differentiable torch; SI units (T, A m^2, A, m)."""
from .base import FieldModel, Superposition, TimeVarying, UniformField
from .magnets import CuboidMagnet, CylinderMagnet, MagnetField, SphereMagnet
from .sources import DipoleSet
from .dipole import (MU0, dipole_dipole_force, dipole_field, dipole_field_gradient, dipole_force, dipole_torque,
                     five_to_gradient, force_from_gradient, force_map, gradient_to_five, moment_from_remanence)

__all__ = [
    "FieldModel", "Superposition", "TimeVarying", "UniformField", "CuboidMagnet", "CylinderMagnet",
    "MagnetField", "SphereMagnet", "DipoleSet", "MU0", "dipole_dipole_force", "dipole_field",
    "dipole_field_gradient", "dipole_force", "dipole_torque", "five_to_gradient", "force_from_gradient",
    "force_map", "gradient_to_five", "moment_from_remanence",
]
