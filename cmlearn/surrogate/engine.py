"""Real-time rollout of a shipped surrogate checkpoint on a scene (no Lightning needed).

    engine = Surrogate.load("checkpoints/semicircle.pt")
    positions, wall = engine.run_scene(engine.task.scene_by_name("semicircle_heldout"))

``step(hist, wrench)`` is the batch-1 step a controller calls; ``compile()`` swaps in a step
compiled ahead of time per input shape (:func:`physics.programs.compile_program`: the LSTM
decomposed into matrix products and fused gates, a few us of call overhead; its compile time, a
few seconds, is not part of any step latency figure). A mirrored model (``reflections``) on a scene
that is itself mirror symmetric (its initial shape and every force, e.g. Simulation III's printed push)
runs its rollout with one image per coset of the scene's symmetries (``run_scene``; by hand:
``with engine.symmetric(axes):``), the same step in fewer operations. A rollout steps through
:meth:`Surrogate.stepper`, which carries each node's LSTM states from step to step (each frame runs through
the LSTM once: :meth:`~cmlearn.models.NodeLSTMSurrogate.carried_step`); on a CUDA device ``stepper(..., graph=True)``
replays each step as one recorded CUDA graph. A task with its own rollout (the
magnetic rod's closed loop, :mod:`cmlearn.surrogate.magnetic`) compiles that whole loop step through
:meth:`Surrogate.program`.
"""
from __future__ import annotations

import functools
import time
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import Tensor

from cmlearn.data.tasks import SurrogateTask, get_task
from cmlearn.data.windows import node_wrench
from physics.programs import compile_program

from .checkpoint import CheckpointError, load_checkpoint

__all__ = ["Stepper", "Surrogate", "SurrogateDivergence", "check_rollout", "check_scene", "load_checkpoints"]


def median_latency(call, n: int, warmup: int) -> float:
    """Seconds per ``call()``: the median of ``n`` timed calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        call()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return sorted(times)[n // 2]


def check_scene(task: SurrogateTask, scene) -> None:
    """TypeError unless ``scene`` is a scene, ValueError unless its rod is ``task``'s (nodes and length: a surrogate
    knows its nodes by their index along that rod) and clamped as in the task's scenes (``chosen`` base position and
    rotation: the magnetic rod's hanging and planar set-ups share one rod)."""
    if not (hasattr(scene, "rod") and hasattr(scene, "initial_configuration")):
        raise TypeError(f"scene: expected a physics Scene (e.g. get_task({task.name!r}).scene_by_name(NAME)), "
                        f"got {type(scene).__name__}")
    base, rod = task.base_scene(), scene.rod
    own = base.rod
    if rod.n_nodes != own.n_nodes or abs(rod.length - own.length) > 1e-9 * own.length:
        raise ValueError(f"scene {scene.name!r}: its rod ({rod.n_nodes} nodes, {rod.length:.4g} m) is not the rod of "
                         f"task {task.name!r} ({own.n_nodes} nodes, {own.length:.4g} m), which this surrogate models")
    for key in ("base_position", "base_rotation"):
        a, b = scene.chosen.get(key), base.chosen.get(key)
        if (a is None) != (b is None) or (a is not None and not torch.allclose(
                torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64), atol=1e-12)):
            raise ValueError(f"scene {scene.name!r}: its rod is clamped otherwise ({key} {a}) than in task "
                             f"{task.name!r} ({b}), whose clamp this surrogate learned: use that task's scenes")
    if (scene.base_motion is None) != (base.base_motion is None):
        raise ValueError(f"scene {scene.name!r}: its base {'moves' if base.base_motion is None else 'is fixed'}, "
                         f"unlike in task {task.name!r}, whose clamp this surrogate learned")
    if not torch.allclose(torch.tensor(scene.gravity, dtype=torch.float64),
                          torch.tensor(base.gravity, dtype=torch.float64), rtol=0, atol=1e-12):
        raise ValueError(f"scene {scene.name!r}: its gravity {tuple(scene.gravity)} is not that of task {task.name!r} "
                         f"{tuple(base.gravity)}, which this surrogate has no input for (it would be left out)")
    if not task.custom:
        for what in ("torque", "field"):
            if getattr(scene.loads, what) is not None:
                raise ValueError(f"scene {scene.name!r}: loads.{what} is set, which a surrogate of task "
                                 f"{task.name!r} has no input for (it sees forces on nodes {list(task.wrench_nodes)} "
                                 f"only); it would be left out")


class SurrogateDivergence(RuntimeError):
    """A free-running surrogate rollout went non-finite or left every shape the rod can take."""


def check_rollout(points: Tensor, task: SurrogateTask, length: float) -> None:
    """Raise :class:`SurrogateDivergence`, naming the first step, its time and the tracked node, where a
    rollout's points (T, n_tracked, 3) are non-finite or some point has moved more than twice the rod's
    ``length`` plus 5 cm (markers off the rod included) from where it started: a rod clamped at one end
    cannot move any of its points farther."""
    d = (points - points[:1]).norm(dim=-1)
    bad = ~torch.isfinite(d) | (d > 2 * length + 0.05)
    if bool(bad.any()):
        k, i = (int(x) for x in bad.nonzero()[0])
        raise SurrogateDivergence(
            f"the {task.name!r} surrogate diverged at step {k} (t = {k * task.delta:.3f} s): tracked node "
            f"{task.tracked[i]} is {float(d[k, i]):.3g} m from its start, more than a {length:g} m rod allows")


class Surrogate:
    def __init__(self, model, meta: dict):
        self.model, self.meta = model.eval(), meta
        self.task: SurrogateTask = get_task(meta["task"])
        for key, want in (("delta", self.task.delta), ("tracked", list(self.task.tracked)),
                          ("modeled", list(self.task.modeled))):
            if key in meta and meta[key] != want:
                raise CheckpointError(f"checkpoint for task {meta['task']!r} has {key} = {meta[key]}, but the task "
                                      f"now defines {want}: retrain it with scripts/train_surrogate.py")
        model.freeze_features()
        self._step = self._eager_step
        self._programs = None  # compiled programs by key and input shapes, after compile()
        self._rest_ref = self._rest_key = self._rest = None

    @classmethod
    def load(cls, path: str | Path, task: str | None = None) -> "Surrogate":
        return cls(*load_checkpoint(path, task=task))

    @property
    def eta(self) -> int:
        return self.model.config.eta

    def step(self, hist: Tensor, wrench: Tensor, ref: Tensor) -> Tensor:
        """Next positions (B, K, 3) of the modelled nodes from the history (B, eta+1, n_tracked, 3), the node
        forces (B, K, 3) and the reference (initial) shape (B, n_tracked, 3). A ``rest_anchor`` model's
        output at rest is computed once per reference tensor (again when it is replaced or changed in
        place). A ``chord_projection`` model then moves them so that every tracked chord keeps its length in
        ``ref``, the anchors held where the last frame has them (clamped)."""
        try:
            pk = self._step(hist, wrench, ref, self.rest_accel(ref))
        except Exception:  # checked only on failure: a check on every call would cost the real-time step
            self.model.check_inputs(hist, ref, wrench)
            raise
        if self.model.config.chord_projection:
            idx = self.model.idx_modeled
            with torch.no_grad():
                pk = self.model.project_chords(hist[:, -1].index_copy(1, idx, pk), ref)[:, idx]
        return pk

    def rest_accel(self, ref: Tensor) -> Tensor | None:
        """The model's :meth:`~cmlearn.models.NodeLSTMSurrogate.rest_accel` of ``ref``, cached; ``None`` for
        a model without the rest anchor."""
        if not self.model.config.rest_anchor:
            return None
        key = (ref._version, ref.shape, ref.dtype, self.model.symmetry_axes)
        # the tensor itself is kept and compared, not its id: a new reference tensor can take a freed one's id
        if self._rest_ref is not ref or key != self._rest_key:  # no_grad only here: a microsecond a step
            with torch.no_grad():
                self._rest_ref, self._rest_key, self._rest = ref, key, self.model.rest_accel(ref)
        return self._rest

    @contextmanager
    def symmetric(self, axes: tuple[int, ...]):
        """Within it, step as for inputs invariant under the model's reflections of these world ``axes``
        (fewer images: :meth:`~cmlearn.models.NodeLSTMSurrogate.use_symmetry`; from :meth:`scene_symmetry`);
        after it, as before. :meth:`run_scene` steps a scene so."""
        before = self.model.symmetry_axes
        self.model.use_symmetry(axes)
        try:
            yield self
        finally:
            self.model.use_symmetry(before)

    def scene_symmetry(self, scene, wrench: Tensor) -> tuple[int, ...]:
        """The model's reflection axes under which the scene's initial shape and node forces (n_steps, K, 3)
        are invariant (to 1e-6 of the rod length and of the force scale), so that the rollout stays so."""
        return self._symmetry(self._initial_points(scene), wrench)

    def _symmetry(self, p0: Tensor, wrench: Tensor) -> tuple[int, ...]:
        """:meth:`scene_symmetry` from the scene's initial tracked points (n_tracked, 3)."""
        return self.model.invariant_axes(p0[None, None], wrench[None]) if self.model.config.reflections else ()

    def _initial_points(self, scene) -> Tensor:
        """The tracked nodes' initial positions (n_tracked, 3), float32."""
        check_scene(self.task, scene)
        return scene.initial_configuration()["p"][list(self.task.tracked)].float()

    @torch.no_grad()
    def _eager_step(self, hist: Tensor, wrench: Tensor, ref: Tensor, rest: Tensor | None) -> Tensor:
        return self.model(hist, wrench, ref, rest=rest)

    def compile(self, gemm_templates: bool = True, fast_exp: bool = True) -> "Surrogate":
        """Run :meth:`step` (and a task's own closed loop, :meth:`program`) through programs compiled for each
        new input shape, of the model's ``program=True`` form (same results to float round-off;
        ``torch.compile`` of the step did not help: the LSTM stays one opaque call). Programs track no
        gradients, so the step skips ``no_grad`` (a microsecond a call). ``gemm_templates`` False compiles in
        about half the time to programs about half as fast (tests). ``fast_exp``: the sigmoids' and tanhs' ``exp``
        in the CPU programs as ATen's inline polynomial (3 units in the last place measured, Sleef's call 1; 4-5 % less
        time a step: :func:`~physics.programs.compile_program`)."""
        model = self.model
        self._gemm_templates, self._fast_exp = gemm_templates, fast_exp

        def fn(h, w, r, *rest):  # the rest output only where the model is anchored (make_fx counts args)
            return model(h, w, r, program=True, rest=rest[0] if rest else None)

        def make(program: bool):
            return fn

        def step(hist: Tensor, wrench: Tensor, ref: Tensor, rest: Tensor | None) -> Tensor:
            args = [hist, wrench, ref] + ([] if rest is None else [rest])
            return self.program(("step", model.symmetry_axes), make, args)(*args)

        self._programs = {}
        self._step = step
        return self

    def program(self, key, make, args: list):
        """The function ``make(program)`` builds, for inputs shaped as ``args``: in the model's eager form
        (``program`` False) or, after :meth:`compile`, compiled from its ``program=True`` form, once per ``key``
        (what else the function depends on) and input shapes. For a task's own rollout (the magnetic rod's
        closed loop), which calls it at every step. The compiled programs are the CPU's: ValueError for inputs
        elsewhere (on a CUDA device the eager engine's step is recorded as a graph instead, :class:`Stepper`)."""
        if self._programs is None:
            return make(False)
        elsewhere = {str(a.device) for a in args if a.device.type != "cpu"}
        if elsewhere:
            raise ValueError(f"compile(): the compiled steps run on the CPU, but the inputs are on {sorted(elsewhere)}: "
                             f"on a CUDA device use an engine that is not compiled, with stepper(..., graph=True)")
        full = (key,) + tuple((a.shape, a.stride(), a.dtype) for a in args)
        prog = self._programs.get(full)
        if prog is None:
            prog = self._programs[full] = compile_program(make(True), args, gemm_templates=self._gemm_templates,
                                                             direct=True, fast_exp=self._fast_exp)
        return prog

    def scene_wrench(self, scene, n_steps: int) -> Tensor:
        """Node forces (n_steps, K, 3) at the interval midpoints, as in the training data."""
        if not (isinstance(n_steps, int) and n_steps >= 0):
            raise ValueError(f"scene_wrench: n_steps must be an integer >= 0, got {n_steps!r}")
        W = torch.zeros(n_steps, len(self.task.wrench_nodes), 3, dtype=torch.float32)
        force, idx, d = scene.loads.force, list(self.task.wrench_nodes), self.task.delta
        if force is not None:
            for k in range(n_steps):
                f = scene.loads.evaluate_force(torch.tensor((k + 0.5) * d, dtype=torch.float64))
                if f is None:
                    continue
                unseen = f.clone()
                unseen[..., idx, :] = 0  # what acts on nodes the model has no input for
                unseen = (unseen != 0).any(-1).reshape(-1, f.shape[-2]).any(0)
                if bool(unseen.any()):
                    raise ValueError(f"scene {scene.name!r}: a force acts on node {int(unseen.nonzero()[0, 0])} at "
                                     f"t = {(k + 0.5) * d:.4g} s, but a surrogate of task {self.task.name!r} sees "
                                     f"forces on nodes {idx} only (it would be left out)")
                W[k] = f[..., idx, :].float()
        return node_wrench(W, self.task.wrench_nodes, self.task.modeled)

    @property
    def device(self) -> torch.device:
        """Where the model is (``engine.model.to(device)`` moves it)."""
        return next(self.model.parameters()).device

    @torch.no_grad()
    def run_scene(self, scene, duration: float | None = None, graph: bool = False) -> tuple[Tensor, float]:
        """Free-running prediction of the tracked nodes (T, n_tracked, 3), T = steps + 1 (from rest in the
        scene's initial shape), on the model's :attr:`device`, and the wall time of the rollout including the force
        evaluation (on a CUDA device up to its last step's end). ``graph``: each step one CUDA-graph replay
        (:class:`Stepper`; the model on a CUDA device). A task with its own physics (``task.custom``, e.g. the
        magnetic rod) runs its closed-loop rollout instead, on the CPU. :class:`SurrogateDivergence` where the rollout
        runs away (:func:`check_rollout`)."""
        self.task.check_duration(duration)
        dev = self.device
        hook = self.task.hook("run_scene")
        if hook is not None:
            if dev.type != "cpu" or graph:
                raise ValueError(f"run_scene: task {self.task.name!r} runs its own closed loop on the CPU only: move "
                                 f"the model to the CPU (it is on {dev}) and leave graph False")
            check_scene(self.task, scene)
            out = hook(self, scene, duration)
            check_rollout(out[0], self.task, scene.rod.length)
            return out
        p0 = self._initial_points(scene)  # checks the scene
        n = int(round((duration or scene.duration) / self.task.delta))
        t0 = time.perf_counter()
        wrench = self.scene_wrench(scene, n)
        p0, wrench = p0.to(dev), wrench.to(dev)
        out = [p0]
        with self.symmetric(self._symmetry(p0, wrench)):
            st = self.stepper(p0[None, None].expand(1, self.eta + 1, -1, -1), p0[None], graph=graph)
            for k in range(n):
                out.append(st.step(wrench[k][None])[0])
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        wall = time.perf_counter() - t0
        out = torch.stack(out)
        check_rollout(out, self.task, scene.rod.length)
        return out, wall

    def stepper(self, hist: Tensor, ref: Tensor, graph: bool = False) -> "Stepper":
        """A rollout from the history (B, eta+1, n_tracked, 3) and the reference shape (B, n_tracked, 3) that carries
        the LSTM states from step to step (:class:`Stepper`): the same steps as :meth:`step`, in fewer operations.
        It steps with the mirror images in use when it is made (:meth:`symmetric`). ``graph``: on a CUDA device, each
        step one replay of a CUDA graph recorded when the stepper is made (:class:`Stepper`)."""
        return Stepper(self, hist, ref, graph=graph)

    @torch.no_grad()
    def step_latency(self, n: int = 2000, warmup: int = 50, scene=None) -> float:
        """Seconds per batch-1 step (median of ``n`` timed steps). Without a ``scene``, :meth:`step` on a synthetic
        shape with every mirror image (any input). Given a ``scene``, its rollout as :meth:`run_scene` steps it
        (:meth:`stepper`, the images its symmetries leave): from its initial shape with its own forces, starting
        again at its end."""
        if n < 1 or warmup < 0:
            raise ValueError(f"step_latency: n must be >= 1 and warmup >= 0, got n={n}, warmup={warmup}")
        K, N, W = self.model.idx_modeled.numel(), self.model.config.n_tracked, self.eta + 1
        if scene is None:
            hist = torch.zeros(1, W, N, 3)
            hist[..., 2] = torch.linspace(0, 0.1, N)
            wrench, ref = torch.zeros(1, K, 3), hist[:, 0]
            return median_latency(lambda: self.step(hist, wrench, ref), n, warmup)
        p0 = self._initial_points(scene)
        n_scene = int(round(scene.duration / self.task.delta))
        if n_scene < 1:
            raise ValueError(f"step_latency: scene {scene.name!r} lasts {scene.duration:g} s, less than one surrogate "
                             f"step ({self.task.delta:g} s)")
        wrench = self.scene_wrench(scene, n_scene)
        times = []
        with self.symmetric(self._symmetry(p0, wrench)):
            for k in range(warmup + n):
                j = k % wrench.shape[0]
                if j == 0:
                    st = self.stepper(p0[None, None].expand(1, W, -1, -1), p0[None])
                t0 = time.perf_counter()
                st.step(wrench[j][None])
                times.append(time.perf_counter() - t0)
        return sorted(times[warmup:])[n // 2]


class Stepper:
    """A surrogate rollout that carries each modelled node's LSTM states from one step to the next
    (:meth:`~cmlearn.models.NodeLSTMSurrogate.carried_step`; made by :meth:`Surrogate.stepper`). ``step(wrench)``
    gives the next frame (B, n_tracked, 3): the modelled nodes predicted, the anchors where the last frame has them
    (clamped), and with ``chord_projection`` every tracked chord given its reference length, as :meth:`Surrogate.step`.
    Made after :meth:`Surrogate.compile`, it runs one compiled program a step (the frame's assembly included).

    Its states start from the history's frames, and a ``rest_anchor`` model's output at rest is taken at the
    states' fixed point at rest, both through the step itself, so that a rod at rest stays there exactly, eager or
    compiled (in a window's arithmetic, :meth:`Surrogate.step`'s, the carried step agrees with it to round-off).

    ``graph`` (inputs and model on a CUDA device): the step, with the copy of its new states and frames into the
    stepper's own, is recorded once into a CUDA graph (:class:`torch.cuda.CUDAGraph`), and each :meth:`step` copies
    the forces in, replays it and returns a copy of the new frame: the same kernels, so the same numbers as the eager
    step on that device, at one launch instead of dozens (at batch 1 the eager step waits on their launches). The
    graph reads the stepper's reference shape and rest output where they are when it is recorded: change them in
    place, not by rebinding. ``python scripts/bench/gpu.py --workloads surrogate_step`` times it."""

    def __init__(self, engine: Surrogate, hist: Tensor, ref: Tensor, graph: bool = False):
        model, E = engine.model, engine.eta
        model.check_inputs(hist, ref)
        if graph and not (hist.is_cuda and ref.is_cuda and engine.device.type == "cuda"):
            raise ValueError(f"graph: a CUDA graph needs the model, hist and ref on a CUDA device, got the model on "
                             f"{engine.device}, hist on {hist.device}, ref on {ref.device}")
        self.model, self.ref, self.axes = model, ref, model.symmetry_axes
        B, K = hist.shape[0], model.idx_modeled.numel()
        # h and c in one tensor (2, eta + 1, G * B * K, hidden): an input and an output fewer, 0.5 us of a 64 us step
        state = hist.new_zeros(2, E + 1, model.img_sign.shape[0] * B * K, model.config.hidden)
        zero, self.rest = hist.new_zeros(B, K, 3), hist.new_zeros(B, K, 3)
        self._wrench_shape, self._wrench_stride = zero.shape, zero.stride()

        def step(state, frames, wrench, ref, rest, program: bool = False):
            pk, a, h, c = model.carried_step(state[0], state[1], frames, wrench, ref, rest, program=program)
            last = frames[:, 1]
            nxt = last.index_copy(1, model.idx_modeled, pk)
            return torch.stack([last, nxt], 1), nxt, a, torch.stack([h, c])

        def make(program: bool):  # a program tracks no gradients; the eager step must not either
            return functools.partial(step, program=True) if program else torch.no_grad()(step)
        frames = hist[:, [0, 0]]
        self._step = engine.program(("carried", self.axes), make, [state, frames, zero, ref, self.rest])
        if model.config.rest_anchor:  # after eta + 1 steps at rest, from any states, every position has seen rest only
            still = ref if model.rest_frame is None else model.rest_frame.to(ref.dtype).expand_as(ref)
            pair, rest_state = torch.stack([still, still], 1), state
            for _ in range(E + 1):
                a, rest_state = self._step(rest_state, pair, zero, ref, self.rest)[2:]
            self.rest = a
        for j in range(E):  # the states after the history's last frame but one, in the step's own arithmetic
            state = self._step(state, hist[:, [max(j - 1, 0), j]], zero, ref, self.rest)[3]
        # canonical strides, as traced (a view of hist is "contiguous" with its batch dim of size 1 strided by 3 frames)
        self.state, self.frames = state, hist[:, -2:].clone(memory_format=torch.contiguous_format)
        self._graph = self._record(zero) if graph else None

    def _record(self, zero: Tensor) -> "torch.cuda.CUDAGraph":
        """The CUDA graph of one step from the stepper's states, frames and force buffer ``zero`` (kept as
        ``self._wrench``) that writes the new states and frames back into them and the new frame into ``self._next``.
        Recorded on the tensors' device after three eager steps on a side stream (lazy initialisations, e.g. cuBLAS's
        workspace, cannot be recorded); the states and frames those steps moved are then put back."""
        bufs = (self.state, self.frames)
        saved = [b.clone() for b in bufs]
        self._wrench = zero
        with torch.cuda.device(zero.device), torch.no_grad():
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(3):
                    self._graph_body()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                self._next = self._graph_body()
            for b, s in zip(bufs, saved):  # recording runs nothing: only the warm-up steps moved them
                b.copy_(s)
        return graph

    def _graph_body(self) -> Tensor:
        frames, nxt, _, state = self._step(self.state, self.frames, self._wrench, self.ref, self.rest)
        self.state.copy_(state)
        self.frames.copy_(frames)
        return nxt

    def step(self, wrench: Tensor) -> Tensor:
        """The next frame (B, n_tracked, 3) for the node forces (B, K, 3) over the step."""
        model = self.model
        if model.symmetry_axes != self.axes:
            raise RuntimeError(f"the stepper was made with the mirror images of axes {self.axes} in use, but the model "
                               f"now uses those of {model.symmetry_axes}: make a new stepper")
        if wrench.shape != self._wrench_shape:
            raise ValueError(f"wrench must be (B, K, 3) = {tuple(self._wrench_shape)}, got {tuple(wrench.shape)}")
        if self._graph is not None:
            if wrench.dtype != self._wrench.dtype:  # a copy would convert it
                raise ValueError(f"wrench must be {self._wrench.dtype} (the model's dtype), got {wrench.dtype}")
            self._wrench.copy_(wrench)
            self._graph.replay()
            nxt = self._next.clone()
            if model.config.chord_projection:
                nxt = model.project_chords(nxt, self.ref)
                self.frames[:, 1].copy_(nxt)
            return nxt
        if wrench.stride() != self._wrench_stride:  # the program's layout
            wrench = torch.empty(self._wrench_shape, dtype=wrench.dtype, device=wrench.device).copy_(wrench)
        self.frames, nxt, _, self.state = self._step(self.state, self.frames, wrench, self.ref, self.rest)
        if model.config.chord_projection:
            nxt = model.project_chords(nxt, self.ref)
            self.frames = torch.stack([self.frames[:, 0], nxt], 1)
        return nxt


def load_checkpoints(paths, magnetic: bool = False) -> tuple[dict, SurrogateTask]:
    """``({file name: Surrogate}, task)`` of checkpoints that must all be of one task, and of a magnetic-rod task
    (a task with its own module) where ``magnetic``; ``ValueError`` otherwise."""
    paths = list(paths)
    if not paths:  # next() of nothing: a bare StopIteration
        raise ValueError("give at least one checkpoint")
    engines = {Path(p).name: Surrogate.load(p) for p in paths}
    tasks = {e.task.name for e in engines.values()}
    task = next(iter(engines.values())).task
    if len(tasks) != 1 or (magnetic and not task.custom):
        raise ValueError(f"give checkpoints of one {'magnetic-rod ' if magnetic else ''}task, not {sorted(tasks)}")
    return engines, task
