"""cmlearn physics: batched, differentiable torch models of rods and magnetic actuation.

Depends only on torch, numpy and scipy.
"""
from .cosserat import CosseratRod, MagnetDipole, Segment
from .cosserat_inverse import FieldFit, fit_uniform_field, tip_angle
from .cosserat_shooting import CosseratSolver, StaticSolution, solve_static
from .errors import SolverError
from .lgvi import LGVI, Boundary, LGVIState, Trajectory, solve_cayley
from .loads import Loads, UniformField
from .rod import CircularSection, Magnet, Material, Rod, RodParams, SquareSection, StabilityEstimate

__all__ = [
    "CosseratRod", "MagnetDipole", "Segment", "FieldFit", "fit_uniform_field", "tip_angle", "CosseratSolver",
    "StaticSolution", "solve_static", "SolverError", "LGVI", "Boundary", "LGVIState", "Trajectory", "solve_cayley", "Loads", "UniformField",
    "CircularSection", "Magnet", "Material", "Rod", "RodParams", "SquareSection", "StabilityEstimate",
]
# 0.1.1: the LGVI's time is its start plus whole steps (loads at window edges); 0.1.2: ellipse_loop refuses a loop its
# equal elements cannot close (Simulation I's loop variants: 1 of seed 0's 32 was closed with a stretched element)
__version__ = "0.1.2"
