"""Classical planners of the thesis's baselines: quadtree obstacle rectangles, ERRT, and attractor
dynamics with Khansari-Zadeh & Billard obstacle modulation; and both as Sub-controller 2 of the
switching controller (:mod:`cmlearn.planning.controllers`, which loads OpenCV lazily); an explored-map
memory with an optimistic grid planner (:mod:`cmlearn.planning.memory`), a further baseline and the
waypoint source of the environment's ``waypoint_lookahead`` option."""
from .attractor import AttractorDynamics, Superellipse, feedback_gain_G
from .controllers import AttractorController, ERRTController, direction_to_action, fit_superellipses
from .errt import ERRT, segment_hits
from .memory import MemoryPlanner, MemoryPlannerController
from .quadtree import covered_mask, merge_rectangles, quadtree_rectangles

__all__ = ["AttractorDynamics", "Superellipse", "feedback_gain_G", "AttractorController", "ERRTController",
           "direction_to_action", "fit_superellipses", "ERRT", "segment_hits", "MemoryPlanner",
           "MemoryPlannerController", "covered_mask", "merge_rectangles",
           "quadtree_rectangles"]
