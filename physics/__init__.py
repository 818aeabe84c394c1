"""cmlearn physics: batched, differentiable torch models of rods and magnetic actuation.

Depends only on torch, numpy and scipy.
"""
from .errors import SolverError
from .lgvi import LGVI, Boundary, LGVIState, Trajectory, solve_cayley
from .loads import Loads, UniformField
from .rod import CircularSection, Magnet, Material, Rod, RodParams, SquareSection, StabilityEstimate

__all__ = [
    "SolverError", "LGVI", "Boundary", "LGVIState", "Trajectory", "solve_cayley", "Loads", "UniformField",
    "CircularSection", "Magnet", "Material", "Rod", "RodParams", "SquareSection", "StabilityEstimate",
]
__version__ = "0.1.0"
