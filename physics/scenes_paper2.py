"""Paper II Simulations I-III (thesis lines 1669-1798): data-generating scenes for node surrogates.

Frames. The thesis's node frames carry the rod axis as their first axis (Tables I.3-I.7:
``E3 = [1, 0, 0]``) and its printed end orientations mix that convention with the plane of the
figure. Here every node frame has body E3 along the centreline tangent and body E2 along the
normal of the plane of the curve, and the printed orientations are reconciled as follows:

* Ellipse (Simulation I): both ends sit at the origin on the ellipse's top vertex where the
  tangent is +x, so both clamped frames equal the tangent frame there (E3 = +x, E2 = +z). The
  printed ``R_y(18.07 deg)`` and ``R_y(341.92 deg)`` are the directions of the first and last
  element chords (a rotation about the loop's normal; the thesis's "y"): 58 elements at equal
  arclength give -18.14 and +18.14 deg; our strain-free node placement (:func:`~physics.shapes.
  ellipse_loop`) gives -/+19.0 deg. For the horizontal ellipse the chords make 0.7 deg, i.e. the
  printed "identity".
* Semicircle (Simulation III): the relative rotation between the two clamped end frames is
  ``R_z(180 deg)``, the printed ``R_z(181.81 deg)`` up to 1.81 deg. One element turns by 1.8 deg, so
  the printed value is most likely the last node's frame counted one element on along an arc turning
  counter-clockwise (from tangent +x, the literal "identity"). Ours is that arc's mirror image, chosen
  and kept: it starts with tangent +y and turns clockwise, so that it stands on its chord along x with
  its apex up and the printed -y force on the middle node pushes the apex towards the chord (on the
  literal arc, chord along y, that force would act along the apex's tangent); counted one element on,
  ours would read ``R_z(-181.8 deg)``.

No gravity: the thesis lists none, and a 55 cm rod of E = 10 MPa and radius 1 cm would sag by
about 45 cm under its own weight. No damping (none is given).

Simulation I's rod is printed only in a figure; its text gives the time step (1e-3 s, "the maximum
constant time step for this simulation") and 50001 samples, i.e. 50 s. Of the printed rods only
Simulation III's (radius 1 cm, E 10 kPa, rho 1000, nu 0.3; the text calls both "a cylindrical rod")
is stable at that step on the loop's 23 mm elements: the explicit update needs dt below 5.0 ms
for it, but 0.16 ms for Simulation II's E = 10 MPa (1e-3 s allows at most E = 0.25 MPa). So the
ellipse uses that rod, dt 1e-3 s and 50 s. Undamped and unloaded, the loop's motion only scales in
time with sqrt(rho/E); what the choice fixes is how many swings the 50 s hold (about 4.5) and where
the 60 % cut falls. An earlier layout ran E = 10 MPa for 5 s at dt 1e-4 s: 32 times as many swings,
by when the loop had turned chaotic (a 10 um nudge at the cut grew to 3.7 mm; at 10 kPa over 50 s
it grows to 19 um, ``docs/rollout_sensitivity.md``).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import torch

from .checks import check_integer, real
from .loads import Loads
from .magnetics.validate import vec3
from .programs import is_tracing
from .rod import CircularSection, Material, Rod
from .scene import Scene
from .shapes import circular_arc, ellipse_loop, ellipse_perimeter

__all__ = ["BUILDERS", "on_mesh", "SquareTipForce", "NodePulse", "path_traced", "pulse_traced", "ellipse",
           "ellipse_horizontal", "square_tracking", "semicircle", "semicircle_heldout"]

_SOFT = Material(E=10e6, density=1000.0, nu=0.3)
_VERY_SOFT = Material(E=10e3, density=1000.0, nu=0.3)
_SECTION = CircularSection(0.02)  # radius 1 cm


def _min_jerk(x):
    """Quintic s(x) = 10x^3 - 15x^4 + 6x^5 and its second derivative on [0, 1] (``x`` a float or a tensor)."""
    x = x.clamp(0.0, 1.0) if torch.is_tensor(x) else min(max(x, 0.0), 1.0)
    return x**3 * (10 - 15 * x + 6 * x * x), x * (60 - 180 * x + 120 * x * x)


def path_traced(t: torch.Tensor, start, length, first, move) -> tuple[torch.Tensor, torch.Tensor]:
    """Position (..., 2) and acceleration (..., 2) at a 0-d tensor ``t`` of minimum-jerk paths given by their
    segments' ``start`` and ``length`` (..., S) (s), first waypoint (..., 2) and segment displacements (..., S, 2), in
    tensor operations with no branch on the time: the sum over all segments of each one's clamped quintic times its
    displacement (a segment of zero displacement, as padding, adds nothing)."""
    start, length, first, move = (a.to(t) for a in (start, length, first, move))
    s, dds = _min_jerk((t - start) / length)
    return first + (s.unsqueeze(-2) @ move).squeeze(-2), ((dds / length**2).unsqueeze(-2) @ move).squeeze(-2)


class SquareTipForce:
    """Open-loop feed-forward force on the tip node so that the tip tracks a square.

    The desired lateral tip path ``x_d(t)`` runs through waypoints ``(0,0) -> (a,a) -> (-a,a) ->
    (-a,-a) -> (a,-a) -> (a,a) -> (0,0)`` with minimum-jerk (quintic) segments, stopping at each
    corner. The force is the single-mode model's inverse ``F = k x_d + m x_d''`` with the
    Euler-Bernoulli tip stiffness ``k = 3 E I / L^3`` and the Rayleigh tip mass ``m = 33/140 rho A L``,
    in the plane normal to the undeformed axis (x, y); no axial force.

    While ``torch.compile`` traces it (``LGVI.compiled_rollout``) the path is evaluated with tensor operations and
    no branch on the time: the sum over all segments of each one's clamped quintic times its displacement (a
    finished segment contributes its whole displacement, a later one nothing, and the quintic's second
    derivative vanishes at both ends), equal to the eager segment search.
    """

    def __init__(self, rod: Rod, half_side: float, durations: tuple[float, ...]):
        E, I = rod.material.E, rod.section.second_moments[0]
        self.k = 3 * E * I / rod.length**3
        self.m = 33 / 140 * rod.line_mass * rod.length
        self.n_nodes = rod.n_nodes
        self._tip = torch.zeros(2, rod.n_nodes, 3, dtype=torch.float64)
        self._tip[0, -1, 0] = self._tip[1, -1, 1] = 1.0
        a = real("SquareTipForce.half_side (m)", half_side)  # NaN gave a NaN force
        self._set_path([(0.0, 0.0), (a, a), (-a, a), (-a, -a), (a, -a), (a, a), (0.0, 0.0)], durations)

    def _set_path(self, waypoints, durations):
        try:
            self.waypoints = [tuple(map(float, w)) for w in waypoints]
            self.durations = tuple(float(d) for d in durations)
        except (TypeError, ValueError):
            raise ValueError(f"waypoints must be (x, y) pairs (m) and durations numbers (s), got {waypoints!r} and "
                             f"{durations!r}") from None
        if len(self.waypoints) < 2 or any(len(w) != 2 for w in self.waypoints):
            raise ValueError(f"waypoints must be at least two (x, y) pairs (m), got {waypoints!r}")
        if len(self.durations) != len(self.waypoints) - 1 or not all(0 < d < math.inf for d in self.durations):
            raise ValueError(f"durations must be one finite positive number (s) per segment ({len(self.waypoints) - 1}), "
                             f"got {self.durations}")
        w = torch.tensor(self.waypoints, dtype=torch.float64)
        d = torch.tensor(self.durations, dtype=torch.float64)
        self._start, self._length, self._first, self._move = torch.cumsum(d, 0) - d, d, w[0], w[1:] - w[:-1]

    def desired(self, t) -> tuple[tuple[float, float], tuple[float, float]]:
        """Desired lateral tip position (x, y) and acceleration at time ``t`` (float or 0-d tensor)."""
        t, t0 = float(t), 0.0
        for (pa, pb), T in zip(zip(self.waypoints, self.waypoints[1:]), self.durations):
            if t < t0 + T:
                s, dds = _min_jerk((t - t0) / T)
                return ((pa[0] + s * (pb[0] - pa[0]), pa[1] + s * (pb[1] - pa[1])),
                        (dds / T**2 * (pb[0] - pa[0]), dds / T**2 * (pb[1] - pa[1])))
            t0 += T
        return self.waypoints[-1], (0.0, 0.0)

    def desired_traced(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`desired` at a 0-d tensor ``t`` in tensor operations: position (2,) and acceleration (2,)."""
        return path_traced(t, self._start, self._length, self._first, self._move)

    def __call__(self, t) -> torch.Tensor:
        if is_tracing():
            x, a = self.desired_traced(t)
            return (self._tip.to(x) * (self.k * x + self.m * a)[..., None, None]).sum(-3)
        (x, y), (ax, ay) = self.desired(t)
        f = torch.zeros(self.n_nodes, 3, dtype=torch.float64)
        f[-1, 0] = self.k * x + self.m * ax
        f[-1, 1] = self.k * y + self.m * ay
        return f


class NodePulse:
    """World force ``amplitude * direction * shape(t)`` on one node for ``t`` in ``[t0, t1)``,
    nothing (``None``: no force evaluation) outside. ``shape`` is ``'constant'`` or ``'cos_pi_t'``
    (``cos(pi t)``, t in seconds)."""

    def __init__(self, n_nodes: int, node: int, direction, amplitude: float, t0: float, t1: float,
                 shape: str = "constant"):
        if shape not in ("constant", "cos_pi_t"):
            raise ValueError(f"NodePulse.shape must be 'constant' or 'cos_pi_t', got {shape!r}")
        # checked here, not at the step where the pulse starts: a 2-vector direction failed in torch there, a NaN
        # amplitude was reported as a diverged state, t1 < t0 (swapped) gave no force at all
        n_nodes = check_integer("NodePulse.n_nodes", n_nodes, lo=2)
        node = check_integer("NodePulse.node", node, lo=-n_nodes)
        if node >= n_nodes:
            raise ValueError(f"NodePulse.node must lie in [-{n_nodes}, {n_nodes - 1}], got {node}")
        t0, t1 = real("NodePulse.t0 (s)", t0), float(t1)
        if math.isnan(t1) or t1 < t0:
            raise ValueError(f"NodePulse.t1 (s) must be >= t0 = {t0:g} (the force acts for t in [t0, t1)), got {t1!r}")
        self.n_nodes, self.node, self.t0, self.t1, self.shape = n_nodes, node, t0, t1, shape
        self.vector = real("NodePulse.amplitude (N)", amplitude) * torch.tensor(vec3("NodePulse.direction", direction),
                                                                              dtype=torch.float64)
        self._on_node = torch.zeros(n_nodes, 1, dtype=torch.float64)
        self._on_node[node] = 1.0

    def __call__(self, t):
        if is_tracing():  # traced (LGVI.compiled_rollout): no branch on the time, zero outside
            return pulse_traced(t, self.t0, self.t1, self.shape == "cos_pi_t", self.vector, self._on_node)
        t = float(t)  # float or 0-d tensor
        if not (self.t0 <= t < self.t1):
            return None
        return self._on_node * (self.vector * (math.cos(math.pi * t) if self.shape == "cos_pi_t" else 1.0))


def pulse_traced(t: torch.Tensor, t0, t1, cos_pi_t, vector, on_node) -> torch.Tensor:
    """Node forces (..., n, 3) of pulses ``vector`` (..., 3) on the nodes ``on_node`` (..., n, 1) (one-hot) for ``t``
    in ``[t0, t1)`` ((...,) s), times ``cos(pi t)`` where ``cos_pi_t`` (bool, ...), at a 0-d tensor ``t`` with no
    branch on the time."""
    t0, t1 = (torch.as_tensor(b, dtype=t.dtype, device=t.device) for b in (t0, t1))
    on = ((t >= t0) & (t < t1)).to(t.dtype)
    scale = torch.where(torch.as_tensor(cos_pi_t, device=t.device), on * torch.cos(math.pi * t), on)
    return on_node.to(t) * (vector.to(t) * scale[..., None]).unsqueeze(-2)


# ------------------------------------------------------------------------------- Simulation I
_ELLIPSE_N = 58
# The one rod of Simulation I: equal elements whose length closes the 0.2 m x 0.6 m ellipse with no
# axial strain (shapes.ellipse_loop); the held-out horizontal ellipse is scaled to close with it.
_ELLIPSE_L = ellipse_loop(_ELLIPSE_N, 0.2, 0.6)[2]
_ELLIPSE_ROD = Rod(_ELLIPSE_N * _ELLIPSE_L, _SECTION, _VERY_SOFT, n_elements=_ELLIPSE_N)
_ELLIPSE_DT, _ELLIPSE_DURATION = 1e-3, 50.0  # printed: max. stable step 1e-3 s, 50001 samples


def _mesh(n_elements: int, printed: int, even: bool = False) -> dict:
    """``chosen`` entries of a scene built on another mesh than the printed one (mesh studies); checks it."""
    if not isinstance(n_elements, int) or n_elements < 2 or (even and n_elements % 2):
        raise ValueError(f"n_elements must be an {'even ' if even else ''}integer >= 2, got {n_elements!r}")
    return {} if n_elements == printed else {"n_elements": n_elements, "printed_n_elements": printed}


def _ellipse_scene(name: str, title: str, width: float, height: float, description: str, thesis: dict,
                   n_elements: int) -> Scene:
    def build(rod_: Rod) -> dict:
        p, R, _ = ellipse_loop(rod_.N, width, height, element_length=rod_.lengths[0])
        return {"p": p, "R": R}

    mesh = _mesh(n_elements, _ELLIPSE_N, even=True)
    rod = _ELLIPSE_ROD if not mesh else Rod(_ELLIPSE_ROD.length, _SECTION, _VERY_SOFT, n_elements=n_elements)
    try:
        p0, _, l0 = ellipse_loop(n_elements, width, height)
    except ValueError as e:  # the closure's bracket fails on a mesh far too coarse for the ellipse
        raise ValueError(f"n_elements={n_elements} is too coarse for the {width} m x {height} m ellipse ({e})") from e
    lopsided = float((p0[:, 0] + p0.flip(0)[:, 0]).abs().max())
    if lopsided > 1e-9 * width:  # the march closed on a loop that is no mirror image of itself
        raise ValueError(f"n_elements={n_elements} is too coarse for the {width} m x {height} m ellipse: its loop "
                         f"closes {lopsided * 1e3:.1f} mm off its mirror symmetry")
    scale = float(rod.lengths[0]) / l0
    mid = n_elements // 2
    return Scene(
        name=name, title=title, description=description, rod=rod, bc="clamped-clamped", dt=_ELLIPSE_DT,
        duration=_ELLIPSE_DURATION, initial=build, nodes_of_interest=(mid, mid - 1, mid + 1),
        node_labels=(f"node {mid + 1} (thesis: 30)", f"node {mid}", f"node {mid + 2}") if mesh else
        ("node 30 (thesis)", "node 29", "node 31"),
        thesis=dict(thesis, width=width, height=height, n_nodes=59, node_of_interest_1based=30, dt=_ELLIPSE_DT,
                    duration=_ELLIPSE_DURATION, samples=50001, dt_max_thesis_model=1e-3),
        chosen={"radius": 0.01, "E": _VERY_SOFT.E, "density": _VERY_SOFT.density, "nu": _VERY_SOFT.nu,
                "material": "Simulation III's rod, the printed rod stable at the printed 1e-3 s step",
                "length": _ELLIPSE_ROD.length, "perimeter": ellipse_perimeter(width, height),
                "ellipse_scale": scale, "nodes": "equal elements with zero axial strain, closing the loop",
                "end_frames": "tangent frame at the origin (E3 = +x, E2 = +z) for both ends", **mesh},
    )


def ellipse(n_elements: int = _ELLIPSE_N) -> Scene:
    """``n_elements`` (even; default the printed 58): the same rod on another mesh, for mesh studies."""
    return _ellipse_scene(
        "ellipse", "Paper II sim. I: closed loop released from an ellipse 0.2 m x 0.6 m", 0.2, 0.6,
        "Paper II Simulation I: a closed loop (58 elements, 59 nodes) bent into an ellipse 0.2 m wide (x) "
        "and 0.6 m high (y) with both end nodes clamped at the origin (its top vertex), released from "
        "rest; the stress-free shape is straight, so the loop oscillates under its own elastic energy. "
        "Chosen (not printed): Simulation III's rod, radius 1 cm, E 10 kPa, rho 1000, nu 0.3 (the one printed "
        "rod stable at the printed 1e-3 s step; Simulation II's 10 MPa needs 0.16 ms). The nodes lie "
        "on the ellipse with every element free of axial strain, which sets the rod length to 1.3283 m "
        "(perimeter 1.3365 m: chords are shorter than arcs). Both clamped frames are the tangent frame "
        "at the origin; the printed R_y(18.07 deg)/R_y(341.92 deg) are the first/last chord directions "
        "about the loop's normal (ours: -/+19.0 deg; nodes at equal arclength would give 18.14 deg). "
        "Node of interest: node 30 of 59 (0-based 29) at (0, -0.6). dt 1e-3 s (printed; dt/dt_max 0.20), 50 s "
        "(the printed 50001 samples); the loop swings about 4.5 times. No gravity, no damping.",
        {"end_orientations_deg": {"first": ("R_y", 18.07), "last": ("R_y", 341.92)},
         "node_of_interest_xy": (-0.01, -0.59),
         "rnn_errors": {"x": (1.57e-3, 0.27e-3), "y": (2.27e-3, 0.46e-3), "z": (0.23e-3, 0.06e-3)}}, n_elements)


def ellipse_horizontal(n_elements: int = _ELLIPSE_N) -> Scene:
    """``n_elements``: as :func:`ellipse`'s."""
    return _ellipse_scene(
        "ellipse_horizontal", "Paper II sim. I held-out: closed loop released from an ellipse 0.6 m x 0.2 m",
        0.6, 0.2,
        "Paper II Simulation I, held-out case: the same rod as 'ellipse' (same element length) bent into "
        "an ellipse 0.6 m wide and 0.2 m high (scaled by 1.00008 so that it closes with that rod), both "
        "ends clamped at the origin (top vertex) with the tangent frame there (the printed 'identity'; "
        "the first chord is 0.7 deg off +x), released from rest. Node of interest: node 30 (0-based 29) "
        "at (0, -0.2). dt 1e-3 s, 50 s. No gravity, no damping.",
        {"end_orientations_deg": {"first": ("identity", 0.0), "last": ("identity", 0.0)},
         "node_of_interest_xy": (-0.01, -0.19),
         "rnn_errors": {"x": (26.33e-3, 3.37e-3), "y": (21.71e-3, 3.70e-3), "z": (4.92e-3, 4.22e-3)}}, n_elements)


# ------------------------------------------------------------------------------- Simulation II
def square_tracking(n_elements: int = 8) -> Scene:
    """``n_elements`` (default the printed 8): the same rod on another mesh, for mesh studies."""
    mesh = _mesh(n_elements, 8)
    rod = Rod(0.55, _SECTION, _SOFT, n_elements=n_elements)
    half, durations = 0.05, (2.0, 3.0, 3.0, 3.0, 3.0, 2.0)
    force = SquareTipForce(rod, half, durations)
    return Scene(
        name="square_tracking",
        title="Paper II sim. II: cantilever whose tip is force-driven around a 10 cm square",
        description=(
            "Paper II Simulation II: a cantilever (radius 1 cm, 55 cm, 8 elements, E 10 MPa, rho 1000, "
            "nu 0.3) clamped at the origin along +z whose tip is driven by lateral forces so that it "
            "tracks a square. Chosen: a 10 cm square (corners at x, y = +-5 cm) entered from the centre in "
            "2 s, each side in 3 s with minimum-jerk stops at the corners, back to the centre in the last "
            "2 s (16 s in all); open-loop feed-forward F = k x_d + m x_d'' with k = 3EI/L^3 = 1.42 N/m and "
            "m = 33/140 of the rod mass (peak force about 0.1 N). dt 1e-4 s (dt/dt_max 0.62). No gravity, "
            "no damping."),
        rod=rod, bc="clamped-free", dt=1e-4, duration=16.0, loads=Loads(force=force),
        nodes_of_interest=(n_elements, n_elements - 1), node_labels=("tip", f"node {n_elements}"),
        thesis={"radius": 0.01, "n_elements": 8, "length": 0.55, "density": 1000.0, "E": 10e6, "nu": 0.3,
                "dt": 1e-4, "duration": 16.0, "samples": 160001, "dt_max_thesis_model": 1e-4,
                "rnn_errors": {"x": (3.58e-3, 1.70e-3), "y": (1.80e-3, 0.69e-3), "z": (2.73e-3, 1.41e-3)}},
        chosen={"square_half_side": half, "segment_durations": durations, "tip_stiffness": force.k,
                "tip_mass": force.m, "plane": "xy (normal to the undeformed axis)", **mesh},
    )


# ------------------------------------------------------------------------------- Simulation III
_SEMI_N = 100
_SEMI_FORCE = 0.02  # N, chosen (not printed): 100 mN snaps the arch through (apex travels ~0.4 m)
_HELDOUT_AMPLITUDE = 0.1  # N, printed: [0, 0, -100 cos(pi t)] mN


def _semicircle_scene(name: str, title: str, force: Callable[[int], NodePulse], description: str, thesis: dict,
                      chosen: dict, n_elements: int) -> Scene:
    """``force(n_elements)``: the scene's pulse, built once the mesh is checked."""
    mesh = _mesh(n_elements, _SEMI_N, even=True)
    rod = Rod(0.6, _SECTION, _VERY_SOFT, n_elements=n_elements)
    quarter = round(14 * n_elements / _SEMI_N)  # the second node of interest: node 15 of the printed 101

    def build(rod_: Rod) -> dict:
        p, R = circular_arc(rod_.arclength.tolist(), math.pi)
        return {"p": p, "R": R}

    base = {"radius": 0.01, "n_elements": _SEMI_N, "length": 0.6, "density": 1000.0, "E": 10e3, "nu": 0.3,
            "dt": 1e-4, "duration": 2.0, "samples": 20001, "end_orientations_deg": {
                "first": ("identity", 0.0), "last": ("R_z", 181.81)}, "force_node_1based": 51}
    return Scene(
        name=name, title=title, description=description, rod=rod, bc="clamped-clamped", dt=1e-4, duration=2.0,
        loads=Loads(force=force(n_elements)), initial=build, nodes_of_interest=(n_elements // 2, quarter),
        node_labels=(f"node {n_elements // 2 + 1} (force)", f"node {quarter + 1}"),
        thesis=dict(base, **thesis),
        chosen=dict({"arc": "semicircle x = R(1 - cos phi), y = R sin phi, R = L/pi = 0.191 m, ends "
                             "(0,0) and (2R,0), apex (R,R); chords lengthened ~1.6e-4 to be strain-free"},
                    **chosen, **mesh),
    )


def semicircle(n_elements: int = _SEMI_N) -> Scene:
    """``n_elements`` (even; default the printed 100): the same rod on another mesh, the force on its middle
    node, for mesh studies."""
    force = lambda n: NodePulse(n + 1, n // 2, (0.0, -1.0, 0.0), _SEMI_FORCE, 0.0, 0.5)  # noqa: E731
    return _semicircle_scene(
        "semicircle", "Paper II sim. III: clamped soft semicircle pushed at its middle for 0.5 s", force,
        "Paper II Simulation III: a very soft rod (radius 1 cm, 60 cm, 100 elements, E 10 kPa, rho 1000, "
        "nu 0.3) bent into a semicircle in the xy-plane (ends clamped at (0,0) and (0.38 m, 0), apex up) "
        "and pushed at its middle node (node 51 of 101) towards the chord (-y) for the first 0.5 s, then "
        "left free. Chosen: force 20 mN (magnitude not printed; 100 mN, the held-out amplitude, snaps "
        "the arch through), which moves the apex about 5 cm; the end frames are tangent frames, related "
        "by R_z(180 deg) (printed 181.81 deg); nodes free of shear/axial strain, so the clamped "
        "semicircle is an exact discrete equilibrium without the force. dt 1e-4 s, 2 s. No gravity, "
        "no damping.",
        {"force_direction": (0.0, -1.0, 0.0), "force_interval": (0.0, 0.5),
         "rnn_errors": {"x": (1.36e-3, 0.78e-3), "y": (0.23e-3, 0.13e-3), "z": (2.22e-3, 0.81e-3)}},
        {"force_magnitude": _SEMI_FORCE}, n_elements)


def semicircle_heldout(n_elements: int = _SEMI_N) -> Scene:
    """``n_elements``: as :func:`semicircle`'s."""
    force = lambda n: NodePulse(n + 1, n // 2, (0.0, 0.0, -1.0), _HELDOUT_AMPLITUDE, 1.0, 2.0 + 1e-9,  # noqa: E731
                                shape="cos_pi_t")
    return _semicircle_scene(
        "semicircle_heldout",
        "Paper II sim. III held-out: semicircle under an out-of-plane 100 cos(pi t) mN force", force,
        "Paper II Simulation III, held-out case: the clamped semicircle of 'semicircle' at rest until "
        "t = 1 s, then the out-of-plane force [0, 0, -100 cos(pi t)] mN on node 51 for t in [1, 2] s "
        "(as printed; a large load for this rod: the apex swings about 0.18 m out of the plane). "
        "dt 1e-4 s, 2 s. No gravity, no damping.",
        {"force": "[0, 0, -100 cos(pi t)] mN", "force_interval": (1.0, 2.0),
         "rnn_errors": {"x": (3.73e-3, 1.25e-3), "y": (2e-3, 0.2e-3), "z": (8.1e-3, 1.2e-3)}},
        {"force_amplitude": _HELDOUT_AMPLITUDE}, n_elements)


BUILDERS = (ellipse, ellipse_horizontal, square_tracking, semicircle, semicircle_heldout)


def on_mesh(scene: Scene, n_elements: int) -> Scene | None:
    """``scene`` (one of the builders' scenes, by name) rebuilt on ``n_elements``, its duration kept, for mesh
    studies; None for a scene that has no builder here."""
    builder = {b.__name__: b for b in BUILDERS}.get(scene.name)
    return None if builder is None else replace(builder(n_elements), duration=scene.duration)
