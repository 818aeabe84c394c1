"""Surrogate tasks: which scene generates the data, which nodes a surrogate models, and how the
training set is widened beyond the single printed scene.

A task names a base scene (Paper II Simulations I-III and the magnetic rod), the surrogate's time
step ``delta`` (a multiple of the scene's LGVI step), the modelled nodes (a sparse chain along the
rod that contains the nodes of interest), the anchors (clamped nodes whose positions are known),
the nodes that carry an input wrench, and a seeded generator of training variants:

* Simulation I (``ellipse``): loops of the same rod bent into ellipses of random aspect ratio released
  from rest, tall or wide with equal odds, ``|log(h/w)|`` uniform in [log 1.25, log 5] (a near-circle
  hardly moves; loops too sharp for 58 strain-free elements, whose chords close short of 97 % of the
  perimeter, beyond 4.85:1 or 1:4.58, are redrawn: the sharpest kept turn by up to 100 deg an element, and
  the tall ones past 4.66:1 close up to 1 cm off their mirror symmetry); aspect ratios within 25 % of the
  held-out horizontal ellipse (1/3) are excluded so that it stays unseen, and within 10 % of the printed
  one (3) so that no variant replays the printed loop's last 40 % (its "unseen samples").
* Simulation II (``square_tracking``): the tip driven through random minimum-jerk waypoint paths
  (the square's feed-forward law, random waypoints within +-7 cm). Held out: a circle and a
  figure eight at the same speed, never drawn as training paths.
* Simulation III (``semicircle``): random force pulses on the middle node, direction uniform on the
  sphere (so out-of-plane motion is seen), 0-100 mN, constant or cos(pi t) shaped, on/off on the
  surrogate's time grid. The printed held-out load is not one of them.
* The magnetic rod (``magnetic_rod``, Data-set IV): random coil-current profiles, minimum-jerk moves
  (0.6-2 s) between current vectors uniform in [-4, 4] A per coil (one in five back to zero), with
  holds of 0.1-1.2 s, from zero current. The held-out profile (sums of slow sinusoids, never
  holding) is of another kind. Its tracked points include two markers per magnet and its data come
  from :mod:`cmlearn.data.magnetic` (``custom``).
* The planar magnetic rod (``magnetic_rod_planar``, the experiment's set-up): the rod horizontal along x,
  random in-plane fields (minimum-jerk moves between fields of 0-8 mT at -100..100 deg from +x, one in
  five back to zero). Held out: a field that sweeps and breathes and never holds.

Variant 0 is always the printed scene itself: its first 60 % trains and its last 40 % is the
"seen scene, unseen samples" evaluation of the thesis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from physics.checks import is_finite_real
from physics.scene import Scene
from physics.programs import is_tracing
from physics.scenes_paper2 import NodePulse, SquareTipForce, _min_jerk, path_traced, pulse_traced
from physics.shapes import ellipse_loop
from physics.scenes import get_scene

__all__ = ["SurrogateTask", "TASKS", "get_task", "BatchedNodeForce", "BatchedNodePulse", "BatchedTipPathForce",
           "TipPathForce"]


class BatchedNodeForce:
    """World node forces (V, n, 3) for V variants: ``fns[v](t) -> (n, 3) or None`` stacked."""

    def __init__(self, fns, n_nodes: int):
        self.fns, self.n_nodes = list(fns), n_nodes

    def __call__(self, t):
        if is_tracing():  # traced (LGVI.compiled_rollout): every variant's force a tensor, no branch on the time
            return torch.stack([fn(t) for fn in self.fns])
        out = torch.zeros(len(self.fns), self.n_nodes, 3, dtype=torch.float64)
        for v, fn in enumerate(self.fns):
            f = fn(t)
            if f is not None:
                out[v] = f
        return out


class BatchedTipPathForce(BatchedNodeForce):
    """:class:`BatchedNodeForce` of feed-forward tip forces along minimum-jerk waypoint paths (``SquareTipForce`` s and
    :class:`TipPathForce` s through waypoints, of one rod), whose traced form evaluates all variants' segments as one
    tensor operation (each variant's padded with segments that do not move), where stacking every variant's traced
    force made a program many times larger (Simulation II's 48 training paths: a compile of minutes)."""

    def __init__(self, fns, n_nodes: int):
        super().__init__(fns, n_nodes)
        if not self.fns or any(not isinstance(f, SquareTipForce) or getattr(f, "curve", None) is not None
                               for f in self.fns):
            raise ValueError("BatchedTipPathForce: every force must be a SquareTipForce or a TipPathForce through "
                             "waypoints")
        f0 = self.fns[0]
        if any((f.k, f.m, f.n_nodes) != (f0.k, f0.m, f0.n_nodes) for f in self.fns) or f0.n_nodes != n_nodes:
            raise ValueError("BatchedTipPathForce: the forces must act on one rod (the same stiffness, mass and nodes)")
        S = max(len(f.durations) for f in self.fns)

        def padded(a, fill):  # (S, ...) with still segments appended
            return torch.cat((a, a.new_full((S - a.shape[0], *a.shape[1:]), fill)))
        self._start = torch.stack([padded(f._start, 0.0) for f in self.fns])  # (V, S)
        self._length = torch.stack([padded(f._length, 1.0) for f in self.fns])  # (V, S)
        self._move = torch.stack([padded(f._move, 0.0) for f in self.fns])  # (V, S, 2)
        self._first = torch.stack([f._first for f in self.fns])  # (V, 2)
        self._tip, self.k, self.m = f0._tip, f0.k, f0.m

    def __call__(self, t):
        if not is_tracing():
            return super().__call__(t)
        x, a = path_traced(t, self._start, self._length, self._first, self._move)  # (V, 2) each
        return (self._tip.to(x) * (self.k * x + self.m * a)[..., None, None]).sum(-3)  # as SquareTipForce's: (V, n, 3)


class BatchedNodePulse(BatchedNodeForce):
    """:class:`BatchedNodeForce` of :class:`~physics.scenes_paper2.NodePulse` s (Simulation III's training pulses),
    whose traced form evaluates every variant's pulse as one tensor operation (stacking each pulse's traced force made
    the program larger and its compile longer)."""

    def __init__(self, fns, n_nodes: int):
        super().__init__(fns, n_nodes)
        if not self.fns or any(not isinstance(f, NodePulse) or f.n_nodes != n_nodes for f in self.fns):
            raise ValueError(f"BatchedNodePulse: every force must be a NodePulse on {n_nodes} nodes")
        self._t0 = torch.tensor([f.t0 for f in self.fns], dtype=torch.float64)
        self._t1 = torch.tensor([f.t1 for f in self.fns], dtype=torch.float64)
        self._cos = torch.tensor([f.shape == "cos_pi_t" for f in self.fns])
        self._vector = torch.stack([f.vector for f in self.fns])  # (V, 3)
        self._on_node = torch.stack([f._on_node for f in self.fns])  # (V, n, 1)

    def __call__(self, t):
        if not is_tracing():
            return super().__call__(t)
        return pulse_traced(t, self._t0, self._t1, self._cos, self._vector, self._on_node)


class TipPathForce(SquareTipForce):
    """Feed-forward tip force ``F = k x_d + m x_d''`` along any lateral path: minimum-jerk segments
    through ``waypoints`` (list of (x, y)) with ``durations``, or a closed ``curve(t) -> ((x, y), (ax, ay))``
    (``t`` a float, or while traced a 0-d tensor: then in tensor operations)."""

    def __init__(self, rod, waypoints=None, durations=None, curve: Callable | None = None):
        super().__init__(rod, 0.0, (1.0,) * 6)
        self.curve = curve
        if curve is None:
            self._set_path(waypoints, durations)

    def desired(self, t):
        return self.curve(float(t)) if self.curve is not None else super().desired(t)

    def desired_traced(self, t):
        if self.curve is None:
            return super().desired_traced(t)
        (x, y), (ax, ay) = self.curve(t)
        return torch.stack((x, y)), torch.stack((ax, ay))


@dataclass(frozen=True)
class SurrogateTask:
    """See the module docstring. ``variants(n, seed)`` returns ``{"p": (V,n,3), "R": ..., "force": fn}``
    for V = n variants (the first the printed scene); ``heldout`` names the held-out scenes.

    ``links`` overrides the model's neighbours of some tracked ids: ``{id: (left, right)}`` (default: the
    previous and next tracked id, none after the last). ``mirrors`` names the reflections the scene's
    physics is symmetric under, each a world axis with its tracked nodes kept (``"same"``) or reversed
    along the rod (``"reversed"``), that a model may be made equivariant under
    (``model_config(mirror=...)``). ``custom`` names a module that replaces the node-position physics for
    tasks that need more (it provides ``simulate``, ``rollout``, ``evaluate``, ``run_scene``, ``short_check`` and
    ``compare_scene``; see :mod:`cmlearn.surrogate.magnetic`). ``equilibrium(scene)``, where given, is the
    rod's node positions (N+1, 3) at rest in the one equilibrium every variant shares, which a rest-anchored
    model holds (``NodeLSTMConfig.rest_shape``) in place of its reference shape."""

    name: str
    scene: str
    delta: float
    modeled: tuple[int, ...]
    anchors: tuple[int, ...]
    wrench_nodes: tuple[int, ...] = ()
    heldout: tuple[str, ...] = ()
    variants: Callable[[Scene, int, int], dict] | None = None
    description: str = ""
    extra_scenes: dict = field(default_factory=dict)
    links: dict = field(default_factory=dict)
    custom: str = ""
    mirrors: dict = field(default_factory=dict)
    equilibrium: Callable[[Scene], torch.Tensor] | None = None

    def __post_init__(self):
        if not (self.delta > 0 and math.isfinite(self.delta)):
            raise ValueError(f"delta must be > 0 seconds, got {self.delta}")
        if sorted(set(self.modeled)) != list(self.modeled):
            raise ValueError("modeled nodes must be strictly increasing")
        if set(self.modeled) & set(self.anchors):
            raise ValueError("a node cannot be both modeled and an anchor")

    def base_scene(self) -> Scene:
        return get_scene(self.scene)

    def scene_by_name(self, name: str) -> Scene:
        if name in self.extra_scenes:
            return self.extra_scenes[name]()
        return get_scene(name)

    @property
    def tracked(self) -> tuple[int, ...]:
        """All nodes the surrogate sees: anchors and modelled nodes, in order along the rod."""
        return tuple(sorted(set(self.modeled) | set(self.anchors)))

    def hook(self, name: str):
        """The ``custom`` module's function ``name`` (None for a plain task)."""
        if not self.custom:
            return None
        import importlib
        return getattr(importlib.import_module(self.custom), name)

    def reflections(self, mirror: str) -> tuple:
        """``NodeLSTMConfig.reflections`` for the axis letters ``mirror`` (each one of ``mirrors``, at most
        once); ValueError naming the declared ones otherwise."""
        if len(set(mirror)) != len(mirror) or not set(mirror) <= set(self.mirrors):
            raise ValueError(f"mirror {mirror!r}: task {self.name!r} declares the reflections "
                             f"{sorted(self.mirrors) or 'none'} (each at most once)")
        reverse = tuple(reversed(range(len(self.tracked))))
        return tuple(("xyz".index(a), reverse if self.mirrors[a] == "reversed" else None) for a in mirror)

    def model_config(self, mirror: str = "", stencil: int = 1, **kw):
        """:class:`~cmlearn.models.NodeLSTMConfig` over the tracked chain with the ``links`` overrides, made
        equivariant under the reflections ``mirror`` (axis letters of ``mirrors``, e.g. ``"zx"``) where given,
        with ``stencil`` rings of neighbours (``NodeLSTMConfig.with_stencil``: each further one beyond the
        overridden first)."""
        from cmlearn.models import NodeLSTMConfig
        if kw.get("rest_anchor") and self.equilibrium is not None and "rest_shape" not in kw:
            rest = self.equilibrium(self.base_scene())[list(self.tracked)]
            kw["rest_shape"] = tuple(tuple(float(x) for x in r) for r in rest.float())
        cfg = NodeLSTMConfig.chain(self.tracked, self.modeled, reflections=self.reflections(mirror), **kw)
        if self.links:
            pos = {n: i for i, n in enumerate(self.tracked)}
            left, right = list(cfg.left), list(cfg.right)
            for j, m in enumerate(self.modeled):
                if m in self.links:
                    left[j], right[j] = (pos[x] for x in self.links[m])
            from dataclasses import replace
            cfg = replace(cfg, left=tuple(left), right=tuple(right))
        return cfg.with_stencil(stencil)

    def check_duration(self, duration) -> None:
        """ValueError unless ``duration`` (s) is None (a scene's own) or a finite time of at least one step
        ``delta`` (rounded to whole steps as the rollouts do: a shorter one gives no frame to predict)."""
        if duration is not None and not (is_finite_real(duration) and round(duration / self.delta) >= 1):
            raise ValueError(f"duration must be a time of at least one surrogate step ({self.delta:g} s on task "
                             f"{self.name!r}), or None for the scene's, got {duration!r}")

    def record_every(self, scene: Scene) -> int:
        k = self.delta / scene.dt
        if abs(k - round(k)) > 1e-9:
            raise ValueError(f"delta {self.delta} must be a multiple of the scene's dt {scene.dt}")
        return int(round(k))


# ------------------------------------------------------------------------------ Simulation I
_HELDOUT_ASPECT, _PRINTED_ASPECT = 0.2 / 0.6, 0.6 / 0.2


def _ellipse_variants(scene: Scene, n: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    rod = scene.rod
    cfg = scene.initial_configuration()
    ps, Rs, aspects = [cfg["p"]], [cfg["R"]], [_PRINTED_ASPECT]
    while len(ps) < n:
        u, sign = torch.rand(2, generator=g).tolist()
        aspect = math.exp((1 if sign < 0.5 else -1) * (math.log(1.25) + u * math.log(5.0 / 1.25)))  # h / w
        if abs(math.log(aspect / _HELDOUT_ASPECT)) < math.log(1.25) or abs(math.log(aspect / _PRINTED_ASPECT)) < math.log(1.1):
            continue
        try:
            p, R, _ = ellipse_loop(rod.N, 1.0, aspect, element_length=rod.lengths[0], min_chord_ratio=0.97)
        except ValueError:  # too sharp for 58 elements free of axial strain: redrawn
            continue
        ps.append(p)
        Rs.append(R)
        aspects.append(aspect)
    return {"p": torch.stack(ps), "R": torch.stack(Rs), "force": None, "info": {"aspect_h_over_w": aspects}}


def _loop_equilibrium(scene: Scene) -> torch.Tensor:
    """Every Simulation I loop has the same rod and clamps (both ends at the origin, tangent +x) and no load,
    so all come to rest in the same shape: the circle the rod closes (of all closed curves of its length,
    the one of least bending energy), the nodes at equal angles. The LGVI holds it still to 2e-12 m over
    5 s (``tests/test_surrogate.py`` checks 0.5 s)."""
    return ellipse_loop(scene.rod.N, 1.0, 1.0, element_length=float(scene.rod.lengths[0]))[0]


# ------------------------------------------------------------------------------ Simulation II
def _square_variants(scene: Scene, n: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    rod = scene.rod
    fns, info = [scene.loads.force], [{"path": "square (printed scene)"}]
    while len(fns) < n:
        k = int(torch.randint(4, 9, (), generator=g))
        pts = [(0.0, 0.0)] + [tuple((torch.rand(2, generator=g) * 0.14 - 0.07).tolist()) for _ in range(k)]
        pts.append((0.0, 0.0))
        dur = [2.0 + 2.0 * float(torch.rand((), generator=g)) for _ in range(len(pts) - 1)]
        scale = 16.0 / sum(dur)  # the printed 16 s, whatever duration a (test) scene runs for
        dur = [d * scale for d in dur]
        fns.append(TipPathForce(rod, pts, dur))
        info.append({"waypoints": pts, "durations": dur})
    cfg = scene.initial_configuration()
    return {"p": cfg["p"].expand(n, -1, -1), "R": None, "force": BatchedTipPathForce(fns, rod.n_nodes),
            "info": info}


def _closed_curve(kind: str, radius: float = 0.05, period: float = 16.0):
    w = 2 * math.pi / period

    def ramp(t):  # minimum-jerk fade-in/out over 2 s keeps the start and end at rest
        return _min_jerk(t / 2.0)[0] * _min_jerk((period - t) / 2.0)[0]

    def curve(t):  # t: a float, or a 0-d tensor (traced)
        sin, cos = (torch.sin, torch.cos) if torch.is_tensor(t) else (math.sin, math.cos)

        def pos(tt):
            a = ramp(tt)
            if kind == "circle":
                return a * radius * sin(w * tt), a * radius * (1 - cos(w * tt))
            return a * radius * sin(w * tt), a * radius * sin(2 * w * tt)
        h = 1e-3
        (x0, y0), (xp, yp), (xm, ym) = pos(t), pos(t + h), pos(t - h)
        return (x0, y0), ((xp - 2 * x0 + xm) / h**2, (yp - 2 * y0 + ym) / h**2)
    return curve


def tracking_heldout_scene(kind: str) -> Scene:
    from dataclasses import replace

    from physics.loads import Loads
    base = get_scene("square_tracking")
    force = TipPathForce(base.rod, curve=_closed_curve(kind))
    return replace(base, name=f"square_tracking_{kind}", loads=Loads(force=force),
                   title=f"Paper II sim. II held-out: the tip driven around a {kind} (5 cm) in 16 s",
                   description=f"Held-out force profile for Simulation II: the square's feed-forward law along a "
                               f"{kind} of radius 5 cm over 16 s with 2 s minimum-jerk fade-in/out; never a "
                               "training path.")


# ------------------------------------------------------------------------------ Simulation III
def _semicircle_variants(scene: Scene, n: int, seed: int, delta: float = 0.01) -> dict:
    g = torch.Generator().manual_seed(seed)
    rod = scene.rod
    node = scene.nodes_of_interest[0]
    fns, info = [scene.loads.force], [{"pulse": "printed: 20 mN along -y for 0.5 s"}]
    steps = int(round(scene.duration / delta))
    while len(fns) < n:
        d = torch.randn(3, generator=g, dtype=torch.float64)
        d = d / d.norm()
        amp = 0.1 * float(torch.rand((), generator=g))
        i0 = int(torch.randint(0, max(steps // 2, 1), (), generator=g))  # a one-step scene: the pulse from its start
        i1 = int(torch.randint(min(i0 + 10, steps), steps + 1, (), generator=g))
        shape = "cos_pi_t" if float(torch.rand((), generator=g)) < 0.5 else "constant"
        fns.append(NodePulse(rod.n_nodes, node, (amp * d).tolist(), 1.0, i0 * delta, i1 * delta, shape))
        info.append({"direction": d.tolist(), "amplitude": amp, "t0": i0 * delta, "t1": i1 * delta, "shape": shape})
    cfg = scene.initial_configuration()
    return {"p": cfg["p"].expand(n, -1, -1), "R": cfg["R"].expand(n, -1, -1, -1),
            "force": BatchedNodePulse(fns, rod.n_nodes), "info": info}


# ------------------------------------------------------------------------------ magnetic rod (Data-set IV)
CURRENT_LIMIT = 4.0  #: A per coil: the magnetic rod's training profiles stay within it


def _setpoint_variants(scene: Scene, n: int, seed: int, label: str, zero, draw, to_currents, info_key: str,
                       info_of) -> dict:
    """Variant 0 the printed profile; the others from ``zero``: minimum-jerk moves (0.6-2 s) between set-points
    ``draw(back, u, g)`` (``back``, one in five: back to zero), holds of 0.1-1.2 s (the first 0.1-1 s), until
    the scene's end. ``to_currents(points) -> (n, C)`` A; ``info_of(points)`` is stored under ``info_key``."""
    from physics.coil_currents import BatchedCurrents, MinJerkCurrents
    g = torch.Generator().manual_seed(seed)
    profiles, info = [scene.loads.field.currents], [{"profile": label}]

    def u(a, b):
        return a + (b - a) * float(torch.rand((), generator=g))
    while len(profiles) < n:
        pts, moves, holds = [zero], [], [u(0.1, 1.0)]
        t = holds[0]
        while t < scene.duration:
            pts.append(draw(float(torch.rand((), generator=g)) < 0.2, u, g))
            moves.append(u(0.6, 2.0))
            holds.append(u(0.1, 1.2))
            t += moves[-1] + holds[-1]
        profiles.append(MinJerkCurrents(to_currents(pts), moves, holds))
        info.append({info_key: info_of(pts), "moves": moves, "holds": holds})
    return {"currents": BatchedCurrents(profiles), "info": info}


def _magnetic_variants(scene: Scene, n: int, seed: int) -> dict:
    """Coil currents drawn uniformly within +-4 A per coil as set-points (:func:`_setpoint_variants`)."""
    zero = torch.zeros(scene.loads.field.currents(0.0).shape[-1], dtype=torch.float64)

    def draw(back, u, g):
        return zero if back else (torch.rand(zero.shape, generator=g, dtype=torch.float64) * 2 - 1) * CURRENT_LIMIT
    return _setpoint_variants(scene, n, seed, "printed (set-point moves to 5 mT fields)", zero, draw, torch.stack,
                              "setpoints", lambda pts: torch.stack(pts).tolist())


def _planar_magnetic_variants(scene: Scene, n: int, seed: int) -> dict:
    """In-plane fields at the planar scene's field point as set-points (:func:`_setpoint_variants`): 0-8 mT
    at -100..100 deg from +x (towards +z)."""
    from physics.scenes_magnetic_rod import planar_setpoints

    def draw(back, u, g):
        b, a = (0.0 if back else u(0.0, 8e-3)), math.radians(u(-100.0, 100.0))
        return b * math.cos(a), b * math.sin(a)
    return _setpoint_variants(scene, n, seed, "printed (6 mT set-points in the x-z plane)", (0.0, 0.0), draw,
                              planar_setpoints, "fields_T", list)


_MAGNET_NODES = dict(modeled=(2, 4, 5, 7, 9, 10, 11, 12, 13, 14), anchors=(0,), wrench_nodes=(4, 5, 9, 10),
                     links={10: (9, 10), 11: (4, 5), 12: (4, 5), 13: (9, 10), 14: (9, 10)},  # 10: the free tip
                     custom="cmlearn.surrogate.magnetic")

TASKS = {
    "ellipse": SurrogateTask(
        name="ellipse", scene="ellipse", delta=0.01,
        modeled=tuple(range(1, 58, 2)), anchors=(0, 58), heldout=("ellipse_horizontal",),
        variants=_ellipse_variants, mirrors={"z": "same", "x": "reversed"}, equilibrium=_loop_equilibrium,
        description="Simulation I: 29 modelled nodes (every other node, including node 30 of 59), both "
                    "clamped ends as anchors, 10 ms surrogate step (the loop moves at up to 0.33 m/s)."),
    "square_tracking": SurrogateTask(
        name="square_tracking", scene="square_tracking", delta=0.01,
        modeled=tuple(range(1, 9)), anchors=(0,), wrench_nodes=(8,),
        heldout=("square_tracking_circle", "square_tracking_figure8"), variants=_square_variants,
        mirrors={"x": "same", "y": "same"},
        extra_scenes={"square_tracking_circle": lambda: tracking_heldout_scene("circle"),
                      "square_tracking_figure8": lambda: tracking_heldout_scene("figure8")},
        description="Simulation II: all 8 free nodes modelled, the clamped base as anchor, the tip force as "
                    "input wrench, 10 ms surrogate step."),
    "semicircle": SurrogateTask(
        name="semicircle", scene="semicircle", delta=0.01,
        modeled=tuple(sorted(set(range(5, 100, 5)) | {14, 86})), anchors=(0, 100), wrench_nodes=(50,),
        heldout=("semicircle_heldout",), variants=_semicircle_variants, mirrors={"z": "same", "x": "reversed"},
        description="Simulation III: 21 modelled nodes (every 5th node, node 15 of 101 and its mirror image 87, "
                    "including the loaded node 51), both clamped ends as anchors, the node-51 force as input, 10 ms step."),
    "magnetic_rod": SurrogateTask(
        name="magnetic_rod", scene="magnetic_rod", delta=0.02, **_MAGNET_NODES,
        heldout=("magnetic_rod_heldout",), variants=_magnetic_variants,
        description="Data-set IV: the two magnet blocks (end nodes 5, 6 and 10, 11 of 11, and two markers on "
                    "each 20 mm out along its E1 and E3 axes, ids 11-14), nodes 3 and 8 between them, the clamp as anchor; the magnets' "
                    "torque and force as equivalent forces on the block end nodes; 20 ms step (50 Hz)."),
    "magnetic_rod_planar": SurrogateTask(
        name="magnetic_rod_planar", scene="magnetic_rod_planar", delta=0.02, **_MAGNET_NODES,
        heldout=("magnetic_rod_planar_heldout",), variants=_planar_magnetic_variants,
        description="Data-set IV in the experiment's planar set-up (the rod horizontal along x, steered in the x-z "
                    "plane): the same points, links and wrench inputs as magnetic_rod, 20 ms step."),
}


def get_task(name: str) -> SurrogateTask:
    try:
        return TASKS[name]
    except KeyError:
        raise KeyError(f"unknown surrogate task {name!r}; valid: {sorted(TASKS)}") from None
