"""Study (docs/surrogates.md, "A position-only step on Simulation I" and "... on Simulation III"): can a node step
that cannot settle into a limit cycle keep Simulation I's swing where the LSTM surrogate does not, and does it carry
over to Simulation III's pushed semicircle?

The step is ``p(t+1) = 2 p(t) - p(t-1) + a(p(t)) + G F(t)``: the second difference of every modelled node is a
function of the current frame only (each node's offsets to its ``r`` tracked neighbours on either side and its
displacement, as changes from the scene's equilibrium (the loop's circle, the semicircle), and a learned node
embedding, through a tanh MLP shared by all nodes), symmetrised over the task's mirrors (x -> -x with the nodes
reversed; on the semicircle also z -> -z) and zero at the equilibrium; on the semicircle a learned constant map ``G``
adds the force on node 51 (at each frame the mean of the dataset's interval forces either side). Whatever ``a`` and
``G`` are, the map ``(p(t-1), p(t)) -> (p(t), p(t+1))`` is time-reversible (run from ``(p(t+1), p(t))`` with the
force played backwards it retraces its frames) and preserves phase-space volume (its Jacobian's determinant is 1), so
it has no attractor: its swing, like the undamped LGVI's, keeps the amplitude its start gives it. What it gives up is
the history: at the 10 ms step the tracked positions alone are not the rod's state (the untracked nodes and the
frames' rotations vibrate at up to several Hz). Reversibility does not stop a force field that is not a gradient
from doing work around a closed path and so pumping energy into the swing; with ``--conservative`` the second
difference is minus the gradient of a learned energy (the network's scalar output summed over the nodes and all
mirror images), so the step is Stormer-Verlet in a potential and keeps a modified energy, as the LGVI keeps its own.

Trained with the rollout loss (squared error of every modelled node, mm) over a schedule of horizons on the task's
variants of seed 0 (the printed scene's first 60 %, the others but the last in full; ``--variants 1``: the printed
scene alone), optionally on trajectories low-passed in time (``--lowpass`` Hz, zero phase, mirrored at both ends: at
the release the motion is even in time), and evaluated as the shipped models are: the node of interest (node 30, y;
node 51, y and z) free-running from the printed scene's 60 % cut, the held-out scene from rest, and the fresh
variants of seeds 1-3 from rest (their score as ``rank_checkpoints.py``'s: the mean over the variants of the largest
axis's max error; and the mean error). The last line is JSON with each stage's figures and the low-pass floor (the
low-passed printed scene's error against the LGVI's over its last 40 %). ``--linear`` fits and evaluates the best
linear step of the same form instead (:class:`LinearStep`), with its fit's residual; ``--latent M`` gives each node M
unobserved coordinates in the same energy (:class:`LatentStep`).

The best Simulation I model of the study (the docs section has every run): 811 s to horizon 256, then a fine-tuning
at 1024 steps from that stage's checkpoint

    python scripts/study_position_only_step.py --conservative --lowpass 1 --horizons 16:300,64:300,256:200 \
      --threads 1 --out runs/cons.pt
    python scripts/study_position_only_step.py --conservative --lowpass 1 --init runs/cons.pt --horizons 1024:150 \
      --lr 2e-4 --batch 16 --threads 2 --out runs/cons_ft.pt
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cmlearn.args import bounded, readable, writable  # noqa: E402
from cmlearn.data import cached_dataset  # noqa: E402
from cmlearn.data.generate import reference_rollout  # noqa: E402
from cmlearn.data.tasks import get_task  # noqa: E402
from cmlearn.data.windows import split_ranges  # noqa: E402
from cmlearn.eval.metrics import axis_errors  # noqa: E402
from cmlearn.io import save_torch_atomic  # noqa: E402
from cmlearn.surrogate.evaluate import fresh_score, interest_slots  # noqa: E402

def mirror_group(mirrors: dict, n: int) -> list[tuple[tuple[float, float, float], list[int]]]:
    """The reflections ``mirrors`` (as :attr:`SurrogateTask.mirrors`: ``{"x": "reversed"}`` is x -> -x with the
    nodes' order reversed, ``{"z": "same"}`` z -> -z with it kept) and all their products, the identity first: the
    axis signs and the node order of each element of the group they generate."""
    group = [((1.0, 1.0, 1.0), list(range(n)))]
    for axis, kind in mirrors.items():
        if axis not in "xyz" or len(axis) != 1 or kind not in ("same", "reversed"):
            raise ValueError(f"mirrors: {axis!r}: {kind!r} is not an axis letter with 'same' or 'reversed'")
        sign = tuple(-1.0 if a == axis else 1.0 for a in "xyz")
        for s, order in list(group):
            group.append((tuple(a * b for a, b in zip(s, sign)), order[::-1] if kind == "reversed" else order))
    return group


def mlp(width: int, hidden: int, depth: int, out: int) -> nn.Sequential:
    """``depth`` tanh layers of ``hidden`` units from ``width`` inputs, then a linear map to ``out``."""
    layers = []
    for _ in range(depth):
        layers += [nn.Linear(width, hidden), nn.Tanh()]
        width = hidden
    return nn.Sequential(*layers, nn.Linear(width, out))


class PositionOnlyStep(nn.Module):
    """The step of the module docstring for a chain of ``n`` tracked nodes whose first and last are anchors.

    ``rest`` (n, 3): the shape the second difference vanishes at, symmetric under ``mirrors`` (see
    :func:`mirror_group`: a reflection maps the frame ``p`` to ``rest + S (p - rest)[order]``). ``force_slot``: the
    tracked node an external force acts on (fixed by every reflection); its effect on the second difference is
    ``G F``, a learned constant (K, 3, 3) map symmetrised over the mirrors, ``g_scale`` (m/N) times the identity on
    that node at the start (a lumped mass ``delta^2 / g_scale``). Being independent of the positions it keeps the
    step reversible (with the force played backwards) and volume-preserving."""

    def __init__(self, rest: Tensor, r: int = 3, hidden: int = 128, depth: int = 2, embedding: int = 8,
                 d_scale: float = 0.05, p_scale: float = 0.2, a_scale: float = 1e-3, conservative: bool = False,
                 mirrors: dict | None = None, force_slot: int | None = None, g_scale: float = 1e-2):
        super().__init__()
        self.conservative = conservative
        n = rest.shape[0]
        mod = list(range(1, n - 1))
        group = mirror_group({"x": "reversed"} if mirrors is None else mirrors, n)
        slot = {k: i for i, k in enumerate(mod)}
        if force_slot is not None and any(order[force_slot] != force_slot for _, order in group):
            raise ValueError(f"force_slot {force_slot} is moved by the mirrors {mirrors!r}")
        self.register_buffer("rest", rest.clone())
        self.register_buffer("mod", torch.tensor(mod))
        self.register_buffer("nbr", torch.tensor([[min(max(k + o, 0), n - 1) for o in range(-r, r + 1) if o]
                                                  for k in mod]))  # (K, 2 r), clamped at the anchors
        self.register_buffer("signs", torch.tensor([s for s, _ in group]))  # (G, 3)
        self.register_buffer("orders", torch.tensor([o for _, o in group]))  # (G, n)
        self.register_buffer("orders_mod", torch.tensor([[slot[o[k]] for k in mod] for _, o in group]))  # (G, K)
        self.d_scale, self.p_scale, self.a_scale, self.g_scale = d_scale, p_scale, a_scale, g_scale
        self.force_slot = force_slot
        self.emb = nn.Parameter(torch.randn(len(mod), embedding) * 0.1)
        self.G = None
        if force_slot is not None:  # starts as a lumped mass: the force accelerates its own node only
            self.G = nn.Parameter(torch.zeros(len(mod), 3, 3))
            with torch.no_grad():
                self.G[slot[force_slot]] = torch.eye(3)
        self.net = mlp(2 * r * 3 + 3 + embedding, hidden, depth, 1 if conservative else 3)

    def reflect(self, p: Tensor, g: int) -> Tensor:
        """Frames (B, n, 3) under the group's element ``g``."""
        return self.rest + (p - self.rest)[:, self.orders[g]] * self.signs[g]

    def reflect_accel(self, a: Tensor, g: int) -> Tensor:
        """Second differences (B, K, 3) of the modelled nodes under the group's element ``g``."""
        return a[:, self.orders_mod[g]] * self.signs[g]

    def _raw(self, p: Tensor) -> Tensor:
        off = p[:, self.nbr] - p[:, self.mod, None] - (self.rest[self.nbr] - self.rest[self.mod, None])
        u = (p[:, self.mod] - self.rest[self.mod]) / self.p_scale
        return self.net(torch.cat([(off / self.d_scale).flatten(2), u, self.emb.expand(p.shape[0], -1, -1)], -1))

    def _all_images(self, p: Tensor) -> Tensor:
        return torch.cat([self.reflect(p, g) for g in range(len(self.signs))])

    def _force(self, p: Tensor) -> Tensor:
        G = len(self.signs)
        if not self.conservative:
            raw = self._raw(self._all_images(p)).chunk(G)
            return sum(self.reflect_accel(a, g) for g, a in enumerate(raw)) / G
        keep = torch.is_grad_enabled()  # training: the force stays differentiable
        with torch.enable_grad():  # minus the gradient of the summed node energies of all mirror images
            x = p if p.requires_grad else p.detach().requires_grad_(True)
            energy = self._raw(self._all_images(x)).sum()
            g = torch.autograd.grad(energy, x, create_graph=keep)[0]
        return -self.d_scale / G * g[:, self.mod]

    def accel(self, p: Tensor) -> Tensor:
        """The second difference (B, K, 3) in metres of frames (B, n, 3): symmetric under the mirrors, zero at
        ``rest``. With ``conservative`` it is minus the gradient of a learned energy (the network's output summed
        over the nodes and all mirror images) less its value at ``rest``: the force of the potential
        ``V(p) - grad V(rest) . p``."""
        return (self._force(p) - self._force(self.rest[None])) * self.a_scale

    def forcing(self, force: Tensor) -> Tensor:
        """The external force's second difference (B, K, 3) for the force (B, 3) on ``force_slot`` (N)."""
        G = sum(self.signs[g][:, None] * self.G[self.orders_mod[g]] * self.signs[g] for g in range(len(self.signs)))
        return torch.einsum("kij,bj->bki", G, force) * (self.g_scale / len(self.signs))

    def rollout(self, prev: Tensor, cur: Tensor, n: int, force: Tensor | None = None) -> Tensor:
        """``n`` frames (B, n, n_tracked, 3) after ``prev``, ``cur`` (B, n_tracked, 3); the anchors stay put.
        ``force`` (B, n, 3): the force on ``force_slot`` at ``cur``'s time and each of the next n - 1 frames."""
        out = []
        for j in range(n):
            a = self.accel(cur)
            if force is not None:
                a = a + self.forcing(force[:, j])
            nxt = cur.clone()
            nxt[:, self.mod] = 2 * cur[:, self.mod] - prev[:, self.mod] + a
            prev, cur = cur, nxt
            out.append(cur)
        return torch.stack(out, 1)

    def rollout_frames(self, prev: Tensor, cur: Tensor, n: int, force: Tensor | None = None) -> Tensor:
        """:meth:`rollout`'s tracked positions (B, n, n_tracked, 3) from states :meth:`start` gives."""
        return self.rollout(prev, cur, n, force)

    def from_rest(self, p0: Tensor, n: int, force: Tensor | None = None) -> Tensor:
        """``n`` frames after ``p0`` (B, n_tracked, 3) released at rest: the frame before is the one after
        without the external force (``p(-h) = p(h)`` for a release, ``p(-h) = p(0)`` at an equilibrium), so the
        first step moves by half the elastic second difference."""
        prev = p0.clone()
        prev[:, self.mod] = p0[:, self.mod] - 0.5 * self.accel(p0)
        return self.rollout(prev, p0, n, force)

    def start(self, frames: Tensor, force: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The (previous, current) state to roll out from after the true ``frames`` (B, T, n, 3) of a run from rest
        under ``force`` (B, T - 1, 3): their last two."""
        return frames[:, -2], frames[:, -1]


class LatentStep(PositionOnlyStep):
    """:class:`PositionOnlyStep` with ``latent`` unobserved coordinates per modelled node (zero at the anchors and at
    rest), stepped with the positions by the same Verlet rule in the same learned energy: its network also sees each
    node's own and its neighbours' latent coordinates, and a quadratic ``|z|^2 / 2`` per node keeps them bounded.
    Their second difference is ``-latent_scale`` times the energy's gradient in them (a constant mass of their own),
    so the map of (previous, current) states is still reversible and volume-preserving: without an attractor, but
    with room for the modes the tracked positions do not hold. Conservative, without mirrors. States are frames
    (B, n, 3 + latent); :meth:`start` estimates the latent part of a run's state by driving it with the true
    positions from rest."""

    def __init__(self, rest: Tensor, latent: int, latent_scale: float = 0.1, **kw):
        super().__init__(rest, conservative=True, mirrors={}, **kw)
        self.latent, self.latent_scale = latent, latent_scale
        r, hidden = self.nbr.shape[1] // 2, self.net[0].out_features
        depth, embedding = sum(isinstance(m, nn.Linear) for m in self.net) - 1, self.emb.shape[1]
        self.net = mlp(2 * r * (3 + latent) + 3 + latent + embedding, hidden, depth, 1)
        self.register_buffer("rest_state", torch.cat([rest, rest.new_zeros(rest.shape[0], latent)], -1))

    def state(self, p: Tensor) -> Tensor:
        """Frames (..., n, 3) with the latent coordinates at rest."""
        return torch.cat([p, p.new_zeros(*p.shape[:-1], self.latent)], -1)

    def _raw(self, x: Tensor) -> Tensor:
        p, z = x[..., :3], x[..., 3:]
        off = p[:, self.nbr] - p[:, self.mod, None] - (self.rest[self.nbr] - self.rest[self.mod, None])
        u = (p[:, self.mod] - self.rest[self.mod]) / self.p_scale
        feats = [(off / self.d_scale).flatten(2), z[:, self.nbr].flatten(2), u, z[:, self.mod],
                 self.emb.expand(x.shape[0], -1, -1)]
        return self.net(torch.cat(feats, -1)) + 0.5 * z[:, self.mod].pow(2).sum(-1, keepdim=True)

    def _force(self, x: Tensor) -> Tensor:
        keep = torch.is_grad_enabled()
        with torch.enable_grad():
            y = x if x.requires_grad else x.detach().requires_grad_(True)
            g = torch.autograd.grad(self._raw(y).sum(), y, create_graph=keep)[0][:, self.mod]
        return -torch.cat([self.d_scale * self.a_scale * g[..., :3], self.latent_scale * g[..., 3:]], -1)

    def accel(self, x: Tensor) -> Tensor:
        return self._force(x) - self._force(self.rest_state[None])

    def forcing(self, force: Tensor) -> Tensor:
        a = super().forcing(force)
        return torch.cat([a, a.new_zeros(*a.shape[:-1], self.latent)], -1)

    def from_rest(self, p0: Tensor, n: int, force: Tensor | None = None) -> Tensor:
        return super().from_rest(self.state(p0), n, force)[..., :3]

    def rollout_frames(self, prev: Tensor, cur: Tensor, n: int, force: Tensor | None = None) -> Tensor:
        return self.rollout(prev, cur, n, force)[..., :3]

    def start(self, frames: Tensor, force: Tensor | None = None) -> tuple[Tensor, Tensor]:
        x = self.state(frames[:, 0])
        prev = x.clone()
        prev[:, self.mod] = x[:, self.mod] - 0.5 * self.accel(x)
        for t in range(frames.shape[1] - 1):
            a = self.accel(x) + (0 if force is None else self.forcing(force[:, t]))
            nxt = self.state(frames[:, t + 1])
            nxt[:, self.mod, 3:] = 2 * x[:, self.mod, 3:] - prev[:, self.mod, 3:] + a[..., 3:]
            prev, x = x, nxt
        return prev, x


class LinearStep(PositionOnlyStep):
    """The best linear step of the same form, ``a = K (p - rest) + G F`` with full matrices (no mirrors imposed),
    fitted by least squares to the second differences of the frames ``t`` of ``ranges`` ((variant, first, last)
    as :func:`split_ranges` gives them) of ``positions`` (V, T, n, 3) under ``force`` (V, T - 1, 3) or None.
    ``residual``: the fit's RMS residual over the RMS second difference (0: a linear step of the frame explains
    them all)."""

    def __init__(self, rest: Tensor, positions: Tensor, force: Tensor | None, ranges, force_slot: int | None):
        super().__init__(rest, mirrors={}, force_slot=force_slot)
        P = positions.double()
        mod = self.mod.tolist()
        rows, targets = [], []
        for v, first, last in ranges:
            u = (P[v, first + 1:last] - rest.double())[:, mod].flatten(1)
            rows.append(u if force is None else torch.cat([u, force[v, first + 1:last].double()], 1))
            targets.append((P[v, first + 2:last + 1] - 2 * P[v, first + 1:last] + P[v, first:last - 1])[:, mod]
                           .flatten(1))
        X, Y = torch.cat(rows), torch.cat(targets)
        scale = X.norm(dim=0).clamp_min(1e-30)  # columns of unit norm; directions no frame spans are left at zero
        W = torch.linalg.lstsq(X / scale, Y, rcond=1e-9, driver="gelsd").solution / scale[:, None]
        self.residual = float((X @ W - Y).pow(2).mean().sqrt() / Y.pow(2).mean().sqrt())  # of the RMS target
        W = W.float()
        self.register_buffer("K", W[:3 * len(mod)])
        self.register_buffer("Gf", W[3 * len(mod):])

    def accel(self, p: Tensor) -> Tensor:
        return ((p - self.rest)[:, self.mod].flatten(1) @ self.K).view(p.shape[0], -1, 3)

    def forcing(self, force: Tensor) -> Tensor:
        return (force @ self.Gf).view(force.shape[0], -1, 3)


def centred(wrench: Tensor) -> Tensor:
    """The force at each frame 0 .. T-2 (..., T-1, 3) from the forces at the interval midpoints (..., T-1, 3) (the
    datasets' ``wrench``), their average either side, nothing before the first frame."""
    pad = torch.cat([torch.zeros_like(wrench[..., :1, :]), wrench], -2)
    return 0.5 * (pad[..., 1:, :] + pad[..., :-1, :])


def lowpassed(p: Tensor, hz: float, rate: float) -> Tensor:
    """Trajectories (V, T, n, 3) low-passed along time (4th-order Butterworth, zero phase, padded by mirroring at
    both ends: at the start, a release from rest, the motion is even in time); the anchors kept."""
    from scipy.signal import butter, sosfiltfilt
    sos = butter(4, hz, fs=rate, output="sos")
    out = torch.from_numpy(sosfiltfilt(sos, p.double().numpy(), axis=1, padtype="even").copy()).to(p.dtype)
    out[:, :, [0, -1]] = p[:, :, [0, -1]]
    return out


# per task: training variants (seed 0), the default reflections, the fresh variant sets (count, seed; the first of
# each is the printed scene, left out), the node of interest's axes reported, and the input scales (metres: neighbour
# offsets, displacement, second difference)
SPECS = {
    "ellipse": dict(variants=32, mirrors="x", fresh=((5, 1), (5, 2), (9, 3)), axes="y",
                    scales=dict(d_scale=0.05, p_scale=0.2, a_scale=1e-3)),
    "semicircle": dict(variants=96, mirrors="xz", fresh=((17, 1), (17, 2), (17, 3)), axes="yz",
                       scales=dict(d_scale=0.03, p_scale=0.05, a_scale=1e-4)),
}


def diverged(pred: Tensor) -> dict | None:
    """``{"diverged_at_step": k}`` for the first of the frames (B, T, n, 3) that is not finite in any rollout."""
    bad = ~pred.isfinite().flatten(2).all(-1).all(0)
    return {"diverged_at_step": int(bad.nonzero()[0]) + 1} if bad.any() else None


def _node_axis_errors(pred: Tensor, true: Tensor, slot: int) -> list[dict]:
    """:func:`axis_errors` of the tracked node ``slot`` in each rollout of ``pred`` (B, T, n, 3)."""
    return [axis_errors(pred[b, :, slot], true[b, :, slot], 1.0) for b in range(pred.shape[0])]


def node_errors(pred: Tensor, true: Tensor, slot: int, axes: str) -> dict:
    """The node of interest's error (mm) per axis of ``axes``: [the mean over the batch of the max, the mean]
    (:func:`diverged`'s report instead where the rollout left the finite numbers)."""
    pred, true = (pred, true) if pred.dim() == 4 else (pred[None], true[None])
    if (bad := diverged(pred)) is not None:
        return bad
    errs = _node_axis_errors(pred, true, slot)
    return {ax: [round(sum(e[ax][k] for e in errs) / len(errs), 2) for k in ("max_mm", "mean_mm")] for ax in axes}


def fresh_errors(pred: Tensor, true: Tensor, slot: int, axes: str) -> list:
    """[:func:`fresh_score` (the mean over the variants of the largest error on any axis, mm), the mean error over
    ``axes``] (:func:`diverged`'s report instead where a rollout left the finite numbers)."""
    if (bad := diverged(pred)) is not None:
        return bad
    errs = _node_axis_errors(pred, true, slot)
    mean = sum(e[ax]["mean_mm"] for e in errs for ax in axes) / (len(errs) * len(axes))
    return [round(fresh_score(errs), 2), round(mean, 2)]


class Study:
    """A task's data and evaluation for the study: the tracked rest shape, the node of interest's slot, the force
    slot (the task's one wrench node, if any) and each case's trajectories with their centred forces."""

    def __init__(self, name: str, data_dir: str, variants: int | None = None):
        self.task, self.spec, self.data_dir = get_task(name), SPECS[name], data_dir
        scene = self.task.base_scene()
        eq = self.task.equilibrium(scene) if self.task.equilibrium else scene.initial_configuration()["p"]
        self.rest = eq[list(self.task.tracked)].float()
        self.slot = interest_slots(self.task, scene)[0]
        if len(self.task.wrench_nodes) > 1:
            raise ValueError(f"task {name!r}: the study takes one input-wrench node, not {self.task.wrench_nodes}")
        self.force_slot = self.task.tracked.index(self.task.wrench_nodes[0]) if self.task.wrench_nodes else None
        rod, n_mod = scene.rod, len(self.task.modeled)
        self.g_scale = self.task.delta ** 2 * n_mod / (rod.line_mass * rod.length)  # m/N: the rod's mass shared
        data = cached_dataset(self.task, variants or self.spec["variants"], 0, data_dir)
        self.positions, self.force = data["positions"], self._forces(data)

    def _forces(self, data: dict) -> Tensor | None:
        return centred(data["wrench"][..., 0, :].float()) if self.force_slot is not None else None

    @torch.no_grad()
    def evaluate(self, model: PositionOnlyStep) -> dict:
        """The node of interest free-running: on the printed scene from its 60 % cut, on the held-out scenes and
        on the fresh variants from rest."""
        axes, slot = self.spec["axes"], self.slot
        P, F = self.positions[0].float(), self.force
        cut = int(round(0.6 * (P.shape[0] - 1)))
        before, after = (None, None) if F is None else (F[:1, :cut], F[:1, cut:])
        prev, cur = model.start(P[None, :cut + 1], before)
        pred = model.rollout_frames(prev, cur, P.shape[0] - 1 - cut, after)[0]
        out = {"seen": node_errors(pred, P[cut + 1:], slot, axes)}
        for name in self.task.heldout:
            p, w, _ = reference_rollout(self.task, name, data_dir=self.data_dir)
            f = self._forces({"wrench": w[None]})
            out[name] = node_errors(model.from_rest(p[None, 0].float(), p.shape[0] - 1, f)[0], p[1:].float(),
                                    slot, axes)
        for n, seed in self.spec["fresh"]:
            d = cached_dataset(self.task, n, seed, self.data_dir)
            q, f = d["positions"][1:].float(), self._forces(d)
            out[f"fresh_seed{seed}"] = fresh_errors(model.from_rest(q[:, 0], q.shape[1] - 1,
                                                                    None if f is None else f[1:]),
                                                    q[:, 1:], slot, axes)
        return out


ARCH = ("task", "r", "hidden", "conservative", "mirrors", "latent")  # what a run's weights fit


def build(study: Study, args: dict) -> PositionOnlyStep:
    """The step a run's ``args`` (the parsed flags, as a run's file keeps them) describe, untrained."""
    kw = dict(r=args["r"], hidden=args["hidden"], force_slot=study.force_slot, g_scale=study.g_scale,
              **study.spec["scales"])
    if args.get("latent"):
        return LatentStep(study.rest, args["latent"], **kw)
    return PositionOnlyStep(study.rest, conservative=args["conservative"],
                            mirrors={ax: study.task.mirrors[ax] for ax in args["mirrors"]}, **kw)


def load_run(study: Study, path: str) -> PositionOnlyStep:
    """The trained step of a run's ``--out`` file, for ``study``'s task."""
    run = torch.load(path, weights_only=True)
    if run["args"].get("task", "ellipse") != study.task.name:
        raise SystemExit(f"--ensemble {path}: a run of task {run['args'].get('task')!r}, not {study.task.name!r}")
    model = build(study, run["args"])
    model.load_state_dict(run["state"])
    return model


class EnsembleStep(PositionOnlyStep):
    """The mean of several steps' second differences (and force maps). The mean of conservative steps is
    conservative too: minus the gradient of their mean energy. Position-only members."""

    def __init__(self, members: list[PositionOnlyStep]):
        if any(isinstance(m, LatentStep) for m in members):
            raise ValueError("EnsembleStep: latent steps have states of their own")
        first = members[0]
        super().__init__(first.rest, mirrors={}, force_slot=first.force_slot)
        self.members = nn.ModuleList(members)

    def accel(self, p: Tensor) -> Tensor:
        return sum(m.accel(p) for m in self.members) / len(self.members)

    def forcing(self, force: Tensor) -> Tensor:
        return sum(m.forcing(force) for m in self.members) / len(self.members)


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="ellipse", choices=sorted(SPECS))
    ap.add_argument("--variants", type=bounded(int, at_least=1), default=None,
                    help="training variants of seed 0 (default: 32 on the ellipse, 96 on the semicircle; "
                    "1: the printed scene's first 60 %% alone, the thesis's protocol)")
    ap.add_argument("--minutes", type=bounded(float, above=0), default=20.0, help="wall-time budget of the training")
    ap.add_argument("--horizons", default="16:200,64:200,256:200,1024:100",
                    help="stages as HORIZON:ITERATIONS, each with its own cosine learning-rate schedule")
    ap.add_argument("--batch", type=bounded(int, at_least=1), default=32)
    ap.add_argument("--lr", type=bounded(float, above=0), default=2e-3)
    ap.add_argument("--hidden", type=bounded(int, at_least=1), default=128)
    ap.add_argument("--r", type=bounded(int, at_least=0), default=3,
                    help="tracked neighbours on either side each node sees")
    ap.add_argument("--mirrors", default=None, help="axis letters of the task's reflections the step is symmetric "
                    "under (default: x on the ellipse, xz on the semicircle)")
    ap.add_argument("--noise", type=bounded(float, at_least=0), default=0.0,
                    help="metres: one random shift of each start's two frames")
    ap.add_argument("--conservative", action="store_true",
                    help="the second difference is minus the gradient of a learned energy (no work around a cycle)")
    ap.add_argument("--latent", type=bounded(int, at_least=0), default=0,
                    help="unobserved coordinates per modelled node (LatentStep: conservative, "
                    "no mirrors, trained on whole runs from rest)")
    ap.add_argument("--lowpass", type=bounded(float, at_least=0), default=0.0,
                    help="Hz: train on trajectories low-passed in time")
    ap.add_argument("--linear", action="store_true", help="only fit and evaluate the least-squares linear step "
                    "(LinearStep) on the same frames, low-passed as asked")
    ap.add_argument("--ensemble", default="", help="only evaluate the mean step of these runs' --out files "
                    "(comma-separated; EnsembleStep)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=2)
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=0)
    ap.add_argument("--data-dir", type=writable(folder=True), default="data")
    ap.add_argument("--init", type=readable(), default="", help="start from this run's weights (its --out file)")
    ap.add_argument("--out", type=writable(), default="runs/position_only_step.pt")
    a = ap.parse_args(argv)
    for name in ("minutes", "batch", "lr", "hidden", "r", "threads", "variants"):
        if getattr(a, name) is not None and getattr(a, name) <= 0:
            ap.error(f"--{name} must be positive, got {getattr(a, name)}")
    if a.ensemble and (a.linear or a.init or a.latent):
        ap.error("--ensemble evaluates trained runs: no --linear, --init or --latent with it")
    if a.latent < 0:
        ap.error(f"--latent must be >= 0, got {a.latent}")
    if a.latent and (a.mirrors or a.lowpass or a.noise or a.linear):
        ap.error("--latent takes no --mirrors (give --mirrors ''), --lowpass, --noise or --linear")
    a.conservative = a.conservative or bool(a.latent)
    a.mirrors = "" if a.latent else SPECS[a.task]["mirrors"] if a.mirrors is None else a.mirrors
    mirrors = get_task(a.task).mirrors
    if len(set(a.mirrors)) != len(a.mirrors) or not set(a.mirrors) <= set(mirrors):
        ap.error(f"--mirrors {a.mirrors!r}: task {a.task!r} has the reflections {sorted(mirrors)}, each at most once")
    try:
        a.stages = [(int(h), int(n)) for h, n in (s.split(":") for s in a.horizons.split(","))]
    except ValueError:
        ap.error(f"--horizons must be HORIZON:ITERATIONS pairs separated by commas, got {a.horizons!r}")
    return a


def main(argv=None) -> dict:
    a = parse(argv)
    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    study = Study(a.task, a.data_dir, a.variants)
    raw, F = study.positions, study.force
    P = lowpassed(raw, a.lowpass, 1.0 / study.task.delta) if a.lowpass else raw
    V, T, n = P.shape[:3]
    moving = (P.std(dim=(0, 1, 2)) > 0).float()  # the axes the data move along (the ellipse stays in its plane)
    train = split_ranges(V, T)["train"]  # the printed scene's first 60 %, variants 1 .. V-2 whole; the last left out
    args = {k: v for k, v in vars(a).items() if k != "stages"}
    cut = int(round(0.6 * (T - 1)))  # the floor of a model of the low-passed motion: the printed scene's last 40 %
    floor = {"lowpass_floor": node_errors(P[0, cut + 1:], raw[0, cut + 1:], study.slot, study.spec["axes"])}
    if a.linear:
        t0 = time.time()
        linear = LinearStep(study.rest, P, F, train, study.force_slot)
        result = {"linear": {"wall_s": round(time.time() - t0, 1), "fit_residual": round(linear.residual, 3),
                             **study.evaluate(linear)}, **floor, "args": args}
        print(json.dumps(result))
        return result
    if a.ensemble:
        members = [load_run(study, path) for path in a.ensemble.split(",")]
        result = {"ensemble": study.evaluate(EnsembleStep(members)), **floor, "args": args}
        print(json.dumps(result))
        return result
    model = build(study, vars(a))
    if a.init:
        init = torch.load(a.init, weights_only=True)
        have = [init["args"].get(k, 0 if k == "latent" else None) for k in ARCH]  # runs before --latent had none
        if have != [getattr(a, k) for k in ARCH]:
            raise SystemExit(f"--init {a.init}: its {ARCH} are {have}")
        model.load_state_dict(init["state"])
    opt = torch.optim.Adam(model.parameters(), lr=a.lr)
    t0, stages = time.time(), []
    for H, iters in a.stages:
        ranges = [(v, first + 1, last - H) for v, first, last in train if last - H > first + 1]  # one before, H after
        if a.latent:  # whole runs from rest: the latent coordinates start at rest too
            ranges = [(v, 0, 1) for v, first, last in train if first == 0 and last >= H]
        if not ranges:
            raise SystemExit(f"--horizons: no training window holds {H} steps after its start")
        weight = torch.tensor([float(b - s) for _, s, b in ranges])
        for k in range(iters):
            if time.time() - t0 > a.minutes * 60:
                break
            for g in opt.param_groups:
                g["lr"] = a.lr * 0.5 * (1 + math.cos(math.pi * k / iters)) + 1e-5
            pick = torch.multinomial(weight, a.batch, replacement=True).tolist()
            vs = torch.tensor([ranges[i][0] for i in pick])
            if a.latent:  # whole runs from rest
                pred = model.from_rest(P[vs, 0], H, None if F is None else F[vs, :H])
                loss = ((pred - P[vs, 1:H + 1])[:, :, 1:-1] * 1e3).pow(2).mean()
            else:
                ts = torch.stack([torch.randint(ranges[i][1], ranges[i][2], ()) for i in pick])
                prev, cur = P[vs, ts - 1], P[vs, ts]
                if a.noise:
                    z = torch.randn(a.batch, n, 3) * a.noise * moving
                    z[:, [0, -1]] = 0.0
                    prev, cur = prev + z, cur + z
                true = torch.stack([P[vs, ts + j] for j in range(1, H + 1)], 1)
                force = None if F is None else torch.stack([F[vs, ts + j] for j in range(H)], 1)
                loss = ((model.rollout(prev, cur, H, force) - true)[:, :, 1:-1] * 1e3).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            if k % 25 == 0:
                print(f"horizon {H} iteration {k}: rollout rmse {loss.sqrt().item():.3f} mm, {time.time() - t0:.0f} s",
                      file=sys.stderr, flush=True)
        save_torch_atomic(a.out, {"state": model.state_dict(), "args": args})
        ev = study.evaluate(model)
        stages.append({"horizon": H, "wall_s": round(time.time() - t0, 1), **ev})
        print(json.dumps(stages[-1]), file=sys.stderr, flush=True)
    result = {"stages": stages, **floor, "args": args}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
