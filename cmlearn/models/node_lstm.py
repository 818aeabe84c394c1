"""Distributed LSTM node surrogate (Paper II, Figure II.2), batched over all modelled nodes.

Each modelled node ``k`` sees a window of its own and its two neighbours' positions over the last
``eta + 1`` surrogate steps (Input Layer I) and the world force on it (Input Layer II). Positions
enter as displacements from a reference configuration ``ref`` (the rollout's initial shape), the
way a finite-element model sees them, so the small motions that drive the dynamics are not buried
under the large constant coordinates:

* Input I, per frame (18 features): the node's displacement ``(p_k - p_k^ref) / D_k``, the changes
  of its neighbour offsets ``((p_j - p_k) - (p_j - p_k)^ref) / d_k`` (j = left, right), its step
  ``(p_k(tau) - p_k(tau - 1)) / v_k`` and the reference offsets ``(p_j - p_k)^ref / L``; with
  ``stencil=2`` (30 features) the same two offset terms for the second neighbours too (``left2``,
  ``right2``: a five-node stencil, as the bending of a rod tracked by positions needs), appended, and with
  ``stencil=3`` (42) for the third (``left3``, ``right3``: seven nodes) after them; through an LSTM;
* Input II: the node force ``/ f_scale`` through two dense layers;
* the LSTM's last output, the force features and a learned node embedding are concatenated (with
  ``mix=1`` also the LSTM outputs of the node's modelled neighbours, with ``mix=2`` theirs too, after them:
  the head becomes a second local layer, so a node's step sees five or seven nodes with a three-node
  stencil, through two layers rather than one, as a convolution along the rod does; zero for an anchor, a
  free end's right and beyond them; with ``mix_width`` each neighbour's output through a shared linear
  projection to that many numbers, so the head's first layer costs less) and a dense head outputs the node's
  normalised second difference ``a_k``; the next position is
  ``p_k(t+1) = 2 p_k(t) - p_k(t-1) + a_k * a_scale_k`` (a Stormer-Verlet-like update, so a zero
  output continues the current motion).

With ``rest_anchor`` the head's output at rest (the history all at the reference shape, no force) is
subtracted from it, so an unloaded rod at its reference shape stays there exactly: for scenes whose
reference shape is an equilibrium (Simulation III's clamped semicircle), where a learned constant
second difference would otherwise make the free-running rollout drift from rest as h^2. It costs
one extra step's evaluation per rollout (:meth:`rest_accel`, passed to every step as ``rest``). Where the
reference shape is not an equilibrium but the scene has one known shape that is (Simulation I's loops,
released from ellipses, all have the same clamps and come to rest as the one circle they close), the
config's ``rest_shape`` gives it (the tracked nodes' positions in the data's world frame, so such a model is
tied to that placement of the clamps): the history all at that shape, no force, is what is subtracted, and
the rod at rest there stays there exactly.

With ``reflections`` the step is made exactly equivariant under a group of mirror symmetries. Each
generator ``(axis, nodes)`` is the reflection that negates a world axis (0, 1 or 2) and, where
``nodes`` is given, maps tracked node ``i`` to ``nodes[i]`` (a rod symmetric about a plane through its
middle, its nodes reversed). Over the group ``G`` they generate (every product of generators; they
commute), ``a(x) = mean_g g a_net(g x)`` over the reflected history, forces and reference. The model
is translation invariant (it sees displacements and offsets only), so any plane normal to the axis
is the same. A rod of circular section without gravity along that axis obeys such a symmetry, so it
costs the model nothing it could have learned; it keeps a motion in a mirror plane (Simulation III's
semicircle pushed in its plane) in that plane exactly, and a symmetric motion symmetric (the same
semicircle's middle node stays on its plane of symmetry), instead of leaking out of them, and every
training window also teaches its mirror images. All ``|G|`` images run as one batch ``|G|`` times the
size through the LSTM and the head. Where the inputs themselves are invariant under a subgroup ``H`` (a
rollout of a symmetric scene: :meth:`invariant_axes`, :meth:`use_symmetry`), ``g h x = g x`` for ``h`` in
``H``, so the mean needs one image per coset: ``a(x) = P_H mean_r r a_net(r x)`` over representatives ``r``
of ``G / H``, ``P_H`` the mean over ``H`` (the group is abelian), the same function with ``|G| / |H|``
images (Simulation III's printed push is invariant under both mirrors: one image instead of four).

With ``chord_projection`` each rollout step ends by moving the modelled nodes (anchors fixed) so that every
chord between consecutive tracked nodes keeps its length in ``ref`` (:meth:`project_chords`): for rods that
hardly stretch, whose free-running rollouts otherwise drift in length.

The LSTM and the dense layers are shared by all nodes (each node runs its own instance over its own
history; the node embedding lets the head specialise), so every surrogate step is one fused LSTM
call over ``batch x nodes`` sequences, and the nodes feed each other's predictions at the next
step. Anchors (clamped nodes) are known inputs. A free end has no right neighbour: its offset is zero.
"""
from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, replace

import torch
from torch import Tensor, nn

__all__ = ["NodeLSTMConfig", "NodeLSTMSurrogate"]


STEP_FEATURES = slice(9, 12)  # Input Layer I's step (p(tau) - p(tau - 1)) / v: after the displacement and the offsets


def n_features(stencil: int) -> int:
    """Input Layer I's width per frame: the displacement and the step (6), and the changes of the offsets and the
    reference offsets of each ring of neighbours (12 a ring)."""
    return 6 + 12 * stencil


@dataclass(frozen=True)
class NodeLSTMConfig:
    n_tracked: int                 # anchors + modelled nodes, in order along the rod
    modeled: tuple[int, ...]       # positions of the modelled nodes in the tracked list
    left: tuple[int, ...]          # tracked index of each modelled node's left neighbour
    right: tuple[int, ...]         # ... right neighbour (the node itself at a free end)
    eta: int = 2                   # history horizon: eta + 1 frames
    hidden: int = 48
    wrench_hidden: int = 16
    embedding: int = 8
    head_hidden: int = 64
    rest_anchor: bool = False      # subtract the output at rest: the reference shape is an equilibrium
    # ... or, where given, this shape (n_tracked rows of x, y, z; the anchors where the data hold them)
    rest_shape: tuple[tuple[float, float, float], ...] | None = None
    chord_projection: bool = False  # after each rollout step, give every tracked chord its reference length
    # generators of the mirror symmetries: (world axis negated, tracked index of each tracked node's mirror
    # image or None for itself), one per axis
    reflections: tuple[tuple[int, tuple[int, ...] | None], ...] = ()
    left2: tuple[int, ...] = ()    # with a five-node stencil: the left neighbour's left neighbour (() otherwise)
    right2: tuple[int, ...] = ()   # ... the right neighbour's right neighbour (the node itself beyond a free end)
    left3: tuple[int, ...] = ()    # with a seven-node stencil: the next beyond left2 (() otherwise)
    right3: tuple[int, ...] = ()   # ... the next beyond right2
    mix: int = 0                   # rings of neighbouring modelled nodes whose LSTM outputs the head also sees
    mix_width: int = 0             # ... each through a shared linear projection to this many numbers (0: none)

    @property
    def stencil(self) -> int:
        """Rings of neighbours each modelled node sees: 1 (left, right), 2 (also left2, right2) or 3 (also left3,
        right3)."""
        return 3 if self.left3 else 2 if self.left2 else 1

    def rings(self) -> list[tuple[str, tuple[int, ...]]]:
        """The neighbour lists of the stencil, ring by ring, left before right: ``[("left", left), ("right",
        right), ...]``."""
        names = [f"{side}{'' if r == 1 else r}" for r in range(1, self.stencil + 1) for side in ("left", "right")]
        return [(name, getattr(self, name)) for name in names]

    def __post_init__(self):
        K = len(self.modeled)
        if K == 0 or len(self.left) != K or len(self.right) != K:
            raise ValueError("modeled, left and right must be non-empty and of equal length")
        if (len(self.left2), len(self.right2)) not in ((0, 0), (K, K)):
            raise ValueError("left2 and right2 (the second neighbours) must both be empty or both as long as modeled")
        if (len(self.left3), len(self.right3)) not in ((0, 0), (K, K)) or (self.left3 and not self.left2):
            raise ValueError("left3 and right3 (the third neighbours) must both be empty or, with left2 and right2, "
                             "both as long as modeled")
        if self.eta < 2:
            raise ValueError(f"eta (history horizon) must be >= 2, got {self.eta}")
        if self.mix not in (0, 1, 2):
            raise ValueError(f"mix (rings of neighbours' LSTM outputs the head sees) must be 0, 1 or 2, "
                             f"got {self.mix!r}")
        if not 0 <= self.mix_width <= self.hidden or (self.mix_width and not self.mix):
            raise ValueError(f"mix_width (the projection of the neighbours' LSTM outputs) must be 0, or in 1..hidden "
                             f"({self.hidden}) with mix >= 1, got {self.mix_width!r} with mix {self.mix}")
        for name in ("hidden", "wrench_hidden", "embedding", "head_hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} (layer width) must be >= 1, got {getattr(self, name)}")
        axes = [r[0] if isinstance(r, tuple) and len(r) == 2 else None for r in self.reflections]
        if any(a not in (0, 1, 2) for a in axes) or len(set(axes)) != len(axes):
            raise ValueError(f"reflections must be (axis, nodes) pairs on distinct world axes 0, 1 or 2, got "
                             f"{self.reflections!r}")
        perms = [m for _, m in self.reflections if m is not None]
        for m in perms:
            if len(m) != self.n_tracked or sorted(m) != list(range(self.n_tracked)) \
                    or any(m[m[i]] != i for i in range(len(m))) or sorted(m[i] for i in self.modeled) != sorted(self.modeled):
                raise ValueError("reflections: each node map must be an involution of the tracked indices that maps "
                                 "modelled nodes to modelled nodes")
        if any(a[b[i]] != b[a[i]] for a in perms for b in perms for i in range(self.n_tracked)):
            raise ValueError("reflections: the node maps must commute (the reflections generate a group)")
        if self.rest_shape is not None and (not self.rest_anchor or len(self.rest_shape) != self.n_tracked
                                            or any(len(r) != 3 for r in self.rest_shape)):
            raise ValueError(f"rest_shape must be n_tracked = {self.n_tracked} rows of 3 coordinates, given with "
                             "rest_anchor")
        for name in ("modeled", "left", "right", "left2", "right2", "left3", "right3"):
            if not all(0 <= i < self.n_tracked for i in getattr(self, name)):
                raise ValueError(f"{name} indices must lie in [0, n_tracked)")

    @staticmethod
    def chain(tracked: tuple[int, ...], modeled: tuple[int, ...], stencil: int = 1, **kw) -> "NodeLSTMConfig":
        """Neighbours along the tracked chain (rod node indices); the last tracked node, if modelled, is a
        free end. ``stencil``: :meth:`with_stencil`."""
        pos = {n: i for i, n in enumerate(tracked)}
        idx = [pos[m] for m in modeled]
        left = [max(i - 1, 0) for i in idx]
        right = [min(i + 1, len(tracked) - 1) for i in idx]
        cfg = NodeLSTMConfig(n_tracked=len(tracked), modeled=tuple(idx), left=tuple(left), right=tuple(right), **kw)
        return cfg.with_stencil(stencil)

    def with_stencil(self, stencil: int) -> "NodeLSTMConfig":
        """This config with one ring of neighbours (``stencil=1``), two (``2``) or three (``3``): each further
        ring is the next tracked nodes beyond the last (the first possibly overridden), clamped at the chain's
        ends, none beyond a free end. A rod tracked by positions alone bends by the curvature at its neighbours,
        which depends on theirs: a five-node stencil."""
        if stencil not in (1, 2, 3):
            raise ValueError(f"stencil must be 1, 2 or 3, got {stencil!r}")
        last, rings, left, right = self.n_tracked - 1, {}, self.left, self.right
        free = {m for m, r in zip(self.modeled, self.right) if r == m}  # free ends: nothing lies beyond them
        for r in (2, 3):
            left = tuple(max(i - 1, 0) for i in left)
            right = tuple(i if i in free else min(i + 1, last) for i in right)
            rings[f"left{r}"], rings[f"right{r}"] = (left, right) if r <= stencil else ((), ())
        return replace(self, **rings)

    def mix_neighbours(self) -> list[tuple[int, ...]]:
        """The modelled nodes whose LSTM outputs each modelled node's head sees besides its own, ring by ring, left
        before right, as slots in ``modeled`` (``len(modeled)``: none, as for an anchor, a free end's right or
        beyond either): the first ring the modelled ``left`` and ``right`` neighbours, each further ring theirs."""
        K, slot = len(self.modeled), {m: j for j, m in enumerate(self.modeled)}
        step = {"left": [slot.get(n, K) for n in self.left] + [K],  # none's neighbour is none
                "right": [K if n == m else slot.get(n, K) for n, m in zip(self.right, self.modeled)] + [K]}
        out, ring = [], {side: list(range(K)) for side in step}
        for _ in range(self.mix):
            for side in ("left", "right"):
                ring[side] = [step[side][j] for j in ring[side]]
                out.append(tuple(ring[side]))
        return out

    def to_dict(self) -> dict:
        return asdict(self)


def _as_shifts(mixed: list[tuple[int, ...]], K: int) -> tuple[int, ...] | None:
    """The mixed neighbours' slots (:meth:`NodeLSTMConfig.mix_neighbours`) as shifts along the modelled nodes, slot
    ``k + d`` for node ``k`` and none beyond either end, where they are that (a chain of modelled nodes); else
    ``None``."""
    shifts = []
    for slots in mixed:
        d = next((s - k for k, s in enumerate(slots) if s < K), 0)
        if any(s != (k + d if 0 <= k + d < K else K) for k, s in enumerate(slots)):
            return None
        shifts.append(d)
    return tuple(shifts)


def _program_sigmoid(x: Tensor) -> Tensor:
    """``sigmoid`` as ``1 / (1 + exp(-x))`` (exact at +-inf: ``exp`` overflows to inf, the result to 0), for
    compiled programs only (no gradients: ``exp`` overflows in the backward). Inductor's vectorised C++
    ``exp`` is cheaper than its ``tanh`` (Sleef's): with these in the LSTM and the head, and the
    head's last layer as in :func:`_program_linear`, the compiled Simulation III step's program takes a quarter
    less time with one, two and four mirror images (``python scripts/bench/surrogate_program.py``)."""
    return 1 / (1 + torch.exp(-x))


def _program_tanh(x: Tensor) -> Tensor:
    """``tanh`` as ``2 sigmoid(2x) - 1`` through :func:`_program_sigmoid` (absolute error a few float
    round-offs)."""
    return 2 * _program_sigmoid(2 * x) - 1


def _program_linear(layer: nn.Linear, x: Tensor) -> Tensor:
    """``layer(x)`` in the form that compiles best: a layer of at most 8 outputs as a product summed over its
    inputs (fused into what follows), not a matrix product: inductor's micro-GEMM took 7 us for the head's 42 x 64 -> 3
    layer, and the mixing head's 42 x 32 -> 8 projection took 3 us more that way in the two-image Simulation III
    step."""
    if layer.out_features > 8:
        return layer(x)
    y = (x.unsqueeze(-2) * layer.weight).sum(-1)
    return y if layer.bias is None else y + layer.bias


def _program_mlp(seq: nn.Sequential, x: Tensor) -> Tensor:
    """``seq(x)`` for a stack of ``nn.Linear`` and ``nn.Tanh`` in the form that compiles best: the tanh as
    :func:`_program_tanh`, the linear layers as :func:`_program_linear`."""
    for layer in seq:
        if isinstance(layer, nn.Tanh):
            x = _program_tanh(x)
        elif isinstance(layer, nn.Linear):
            x = _program_linear(layer, x)
        else:
            raise TypeError(f"_program_mlp: no program form for {type(layer).__name__}")
    return x


class NodeLSTMSurrogate(nn.Module):
    """See the module docstring. Normalisation buffers are set with :meth:`set_scales`."""

    def __init__(self, config: NodeLSTMConfig):
        super().__init__()
        self.config = c = config
        K = len(c.modeled)
        self.n_features = n_features(c.stencil)
        self.lstm = nn.LSTM(self.n_features, c.hidden, batch_first=True)
        self.wrench = nn.Sequential(nn.Linear(3, c.wrench_hidden), nn.Tanh(), nn.Linear(c.wrench_hidden, c.wrench_hidden))
        self.embed = nn.Embedding(K, c.embedding)
        n_in = self._head_own_inputs + 2 * c.mix * (c.mix_width or c.hidden)  # and the neighbours' (projected) outputs
        self.mix_proj = nn.Linear(c.hidden, c.mix_width, bias=False) if c.mix_width else None
        self.head = nn.Sequential(nn.Linear(n_in, c.head_hidden), nn.Tanh(),
                                  nn.Linear(c.head_hidden, c.head_hidden), nn.Tanh(), nn.Linear(c.head_hidden, 3))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)
        rings = c.rings()
        for name, idx in [("modeled", c.modeled)] + rings:
            self.register_buffer(f"idx_{name}", torch.tensor(idx, dtype=torch.long), persistent=False)
        self._rings = [name for name, _ in rings]
        mixed = c.mix_neighbours()
        self.register_buffer("idx_mix", torch.tensor(mixed, dtype=torch.long).t().reshape(-1) if mixed else None,
                             persistent=False)  # (K * 2 mix,): node k's mixed slots, k-major; K for none
        self._mix_shifts = _as_shifts(mixed, K)
        movable = torch.zeros(c.n_tracked)
        movable[list(c.modeled)] = 1.0
        self.register_buffer("movable", movable, persistent=False)  # (n_tracked,): 1 modelled, 0 anchor
        self.register_buffer("rest_frame", None if c.rest_shape is None else torch.tensor(c.rest_shape),
                             persistent=False)  # (n_tracked, 3) from the config
        free_end = torch.tensor([float(r == m) for r, m in zip(c.right, c.modeled)])
        self.register_buffer("has_right", 1.0 - free_end[:, None], persistent=False)
        self.register_buffer("length_scale", torch.ones(()))
        self.register_buffer("disp_scale", torch.ones(K, 3))
        self.register_buffer("rel_scale", torch.ones(K, 6 * c.stencil))
        self.register_buffer("v_scale", torch.ones(K, 3))
        self.register_buffer("a_scale", torch.ones(K, 3))
        self.register_buffer("f_scale", torch.ones(()))
        # the symmetry group: element g maps positions x (..., n_tracked, 3) to sign[g] * x[..., perm[g], :]
        signs, perms = [torch.ones(3)], [list(range(c.n_tracked))]
        for axis, nodes in c.reflections:
            s = torch.ones(3)
            s[axis] = -1.0
            m = list(nodes or range(c.n_tracked))
            signs += [g * s for g in signs]
            perms += [[p[i] for i in m] for p in perms]
        slot = {n: j for j, n in enumerate(c.modeled)}
        self.register_buffer("mirror_sign", torch.stack(signs), persistent=False)  # (G, 3)
        self.register_buffer("mirror_perm", torch.tensor(perms, dtype=torch.long), persistent=False)  # (G, n_tracked)
        self.register_buffer("mirror_perm_modeled", torch.tensor([[slot[p[n]] for n in c.modeled] for p in perms],
                                                                 dtype=torch.long), persistent=False)  # (G, K)
        # freeze_features; buffers, so that .to(device) moves them too (images in use; every image)
        for name in ("_feature_matrix", "_feature_rows", "_feature_blocks", "_carry_rows", "_carry_blocks"):
            for part in ("", "_group"):
                self.register_buffer(name + part, None, persistent=False)
        self.register_buffer("_lstm_stacked", None, persistent=False)  # freeze_features: (F + hidden, 4 hidden)
        self.register_buffer("_gate_scale", torch.tensor([1.0, 1.0, 2.0, 1.0]).repeat_interleave(c.hidden),
                             persistent=False)  # the LSTM's gates i, f, g, o: g's tanh through a sigmoid
        for name in ("_carry_wih", "_carry_whh", "_carry_bias"):  # freeze_features: _carried_weights()
            self.register_buffer(name, None, persistent=False)
        for name in ("_head_w0", "_head_b0"):  # freeze_features: _folded_first_layer()
            self.register_buffer(name, None, persistent=False)
        self.use_symmetry(())  # the images in use (all of G) and the stabiliser projected on (none)

    def invariant_axes(self, frames: Tensor, wrench: Tensor, rtol: float = 1e-6) -> tuple[int, ...]:
        """The axes of the model's reflections under which the inputs of a rollout are invariant: every frame
        (B, T, n_tracked, 3) (histories, the reference, anchors; one mirror plane for all of them, a
        translation along the axis being invisible to the model) and the forces (B, H, K, 3) equal their
        mirror images to ``rtol`` of the rod length (forces: of their scale). The config's ``rest_shape``
        counts as a frame. A model evaluated with :meth:`use_symmetry` of these axes keeps such a rollout
        symmetric, as the whole group does."""
        if self.rest_frame is not None:
            frames = torch.cat([frames, self.rest_frame.to(frames)[None, None].expand(frames.shape[0], 1, -1, -1)], 1)
        tol, tol_f = rtol * float(self.length_scale), rtol * float(self.f_scale)
        worst = lambda x: float(x.abs().max()) if x.numel() else 0.0  # noqa: E731
        axes = []
        for j, (axis, _) in enumerate(self.config.reflections):
            g = 1 << j  # the group element of generator j alone
            d = (frames[..., self.mirror_perm[g], :] * self.mirror_sign[g] - frames).flatten(1, -2)
            shift = d[..., axis]  # one translation along the axis per batch element
            other = torch.cat([d[..., :axis], d[..., axis + 1:]], -1)
            dw = wrench[..., self.mirror_perm_modeled[g], :] * self.mirror_sign[g] - wrench
            if worst(other) <= tol and worst(dw) <= tol_f and worst(shift.amax(1) - shift.amin(1)) <= tol:
                axes.append(axis)
        return tuple(sorted(axes))

    def use_symmetry(self, axes: tuple[int, ...] = ()) -> "NodeLSTMSurrogate":
        """Evaluate the mirrored step for inputs invariant under the reflections of these world ``axes`` (a
        subset of the model's; from :meth:`invariant_axes`): one image per coset of the subgroup ``H`` they
        generate, then the projection on ``H`` (the module docstring). Inputs that are not invariant get wrong
        steps; ``()`` (and ``train()``) returns to the whole group. Re-freezes frozen features."""
        mine = [a for a, _ in self.config.reflections]
        if any(a not in mine for a in axes):
            raise ValueError(f"axes must be among the model's reflection axes {tuple(mine)}, got {tuple(axes)}")
        stab = sum(1 << mine.index(a) for a in axes)
        G = self.mirror_sign.shape[0]
        reps = [g for g in range(G) if not g & stab]  # one element per coset g H
        sub = [g for g in range(G) if not g & ~stab]  # H
        self.symmetry_axes = tuple(sorted(set(axes)))
        dev = self.mirror_perm.device
        for kind, idx in (("img", reps), ("stab", sub)):  # buffers, so that .to(device) moves them too
            idx = torch.tensor(idx, device=dev)
            for name in ("sign", "perm", "perm_modeled"):
                table = getattr(self, f"mirror_{name}")[idx] if kind == "img" or len(sub) > 1 else None
                self.register_buffer(f"{kind}_{name}", table, persistent=False)
        self.register_buffer("img_index", torch.arange(len(reps), device=dev)[:, None], persistent=False)
        self.register_buffer("img_elements", torch.tensor(reps, device=dev), persistent=False)
        self._select_features()
        return self

    def _mean_back(self, y: Tensor, B: int, modeled: bool = True) -> Tensor:
        """``P_H mean_r r^-1 y_r`` of per-image outputs ``y`` (R * B, nodes, 3), image-major, that transform
        like displacements (nodes: the modelled ones, or all tracked with ``modeled=False``)."""
        perm = self.img_perm_modeled if modeled else self.img_perm
        y = (y.unflatten(0, (perm.shape[0], B)).movedim(0, 1)[:, self.img_index, perm] * self.img_sign[:, None]).mean(1)
        if self.stab_sign is not None:
            y = (y[:, self.stab_perm_modeled if modeled else self.stab_perm] * self.stab_sign[:, None]).mean(1)
        return y

    @torch.no_grad()
    def set_scales(self, trajectories, wrench: Tensor, length: float) -> None:
        """Scales from training trajectories (a list of (T_i, n_tracked, 3), each starting at its reference
        shape) and forces (..., K, 3)."""
        if not length > 0:
            raise ValueError(f"length (the rod's, metres) must be > 0, got {length!r}")
        if sum(max(len(p) - 2, 0) for p in trajectories) < 2:
            raise ValueError(f"trajectories must hold at least two second differences (frames t-1, t, t+1) for the "
                             f"scales' spread, got lengths {[len(p) for p in trajectories]}")
        tiny = 1e-9 * length
        disp, rel, v, a = [], [], [], []
        for p in trajectories:
            p = p.double()
            pk = p[:, self.idx_modeled]
            disp.append(pk - pk[:1])
            r = self._offsets(p)
            rel.append(r - r[:1])
            v.append(pk[1:] - pk[:-1])
            a.append(pk[2:] - 2 * pk[1:-1] + pk[:-2])
        self.length_scale.fill_(length)
        self.disp_scale.copy_(torch.cat(disp).std(0).clamp_min(1e3 * tiny))
        self.rel_scale.copy_(torch.cat(rel).std(0).clamp_min(1e2 * tiny))
        self.v_scale.copy_(torch.cat(v).std(0).clamp_min(10 * tiny))
        self.a_scale.copy_(torch.cat(a).std(0).clamp_min(tiny))
        self.f_scale.fill_(float(wrench.abs().max()) if wrench.numel() and wrench.abs().max() > 0 else 1.0)

    def _offsets(self, p: Tensor) -> Tensor:
        """Neighbour offsets (..., K, 6 * stencil) of positions (..., n_tracked, 3), ring by ring (left, right,
        then left2, right2, ...); zero beyond a free end."""
        pk = p[..., self.idx_modeled, :]
        off = [p[..., self.idx_left, :] - pk, (p[..., self.idx_right, :] - pk) * self.has_right]
        return torch.cat(off + [p[..., getattr(self, f"idx_{r}"), :] - pk for r in self._rings[2:]], -1)

    def features(self, hist: Tensor, ref: Tensor) -> Tensor:
        """(B, W, n_tracked, 3) history and (B, n_tracked, 3) reference -> (B, K, W, F) Input Layer I: the
        first ring's 18 features, then 12 for each further ring of the stencil (its offsets' changes and reference
        offsets), so that a widened stencil appends features (:meth:`widen`)."""
        pk = hist[:, :, self.idx_modeled]
        rel0 = self._offsets(ref)[:, None]
        disp = (pk - ref[:, None, self.idx_modeled]) / self.disp_scale
        drel = (self._offsets(hist) - rel0) / self.rel_scale
        step = torch.cat([torch.zeros_like(pk[:, :1]), pk[:, 1:] - pk[:, :-1]], 1) / self.v_scale
        geo = (rel0 / self.length_scale).expand(-1, hist.shape[1], -1, -1)
        outer = [t[..., r:r + 6] for r in range(6, drel.shape[-1], 6) for t in (drel, geo)]
        return torch.cat([disp, drel[..., :6], step, geo[..., :6]] + outer, -1).transpose(1, 2)  # step: STEP_FEATURES

    @torch.no_grad()
    def freeze_features(self) -> "NodeLSTMSurrogate":
        """Inference speed-up. Input Layer I is linear in (history, reference): precompute it as one
        matrix (built by applying :meth:`features` to the unit basis) and, for compiled programs
        (``forward(..., program=True)``), per node, since node ``k``'s features depend only on its own
        and its neighbours' positions: the matrix from those ``(eta + 2) * 3 * (1 + 2 stencil)`` numbers to its
        ``(eta + 1) * F`` features (eagerly one matrix product is faster, compiled the blocks). The same per-node
        blocks of a carried step's newest frame (:meth:`carried_step`, from the last two frames and the reference).
        Every mirror image's matrices are kept; those of the images in use (:meth:`use_symmetry`) are
        taken from them. The LSTM's stacked weights (:meth:`_lstm_last`) are kept too, so that a compiled
        program holds them as one constant (a product with weights computed in the program has no C++ GEMM
        template). Call again after changing the scales; :meth:`unfreeze_features` (or ``train()``)
        returns to the explicit computation."""
        W, K, F = self.config.eta + 1, self.idx_modeled.numel(), self.n_features
        self._feature_matrix_group, self._feature_rows_group, self._feature_blocks_group = self._node_blocks(
            lambda x: self.features(x[:, :W], x[:, W]).reshape(-1, K, W * F), W + 1)
        _, self._carry_rows_group, self._carry_blocks_group = self._node_blocks(
            lambda x: self._newest_features(x[:, :2], x[:, 2]), 3)
        self._lstm_stacked = self._stacked_lstm_weights().contiguous()  # a constant of the program, not an op in it
        self._carry_wih, self._carry_whh, self._carry_bias = (t.contiguous() for t in self._carried_weights())
        self._head_w0, self._head_b0 = (t.contiguous() for t in self._folded_first_layer())
        self._select_features()
        return self

    def _node_blocks(self, fn, n_frames: int) -> tuple[Tensor, Tensor, Tensor]:
        """A map ``fn`` linear in ``n_frames`` frames (D, n_frames, n_tracked, 3) -> (D, K, O) that reads only each
        node's own and its neighbours' positions, frozen for every mirror image ``g`` (``g x = sign * x[flip]``, folded
        into the rows): ``(dense, rows, blocks)``, the dense matrix (D, G, K * O), and per node the rows of the
        flattened input it reads (G, K, n_frames * 3 * (1 + 2 stencil)) and its matrix from them (G, K, rows, O);
        the identity first."""
        N = self.config.n_tracked
        D = n_frames * N * 3
        basis = torch.eye(D, dtype=self.a_scale.dtype, device=self.a_scale.device).reshape(D, n_frames, N, 3)
        dense = fn(basis)
        K, O = dense.shape[1:]
        nodes = torch.stack([self.idx_modeled] + [getattr(self, f"idx_{r}") for r in self._rings], -1)  # (K, 1 + 2 s)
        frame = torch.arange(n_frames, device=nodes.device)[:, None, None] * N
        # (frames, K, 1 + 2 s, 3)
        rows = ((frame + nodes[None]) * 3).unsqueeze(-1) + torch.arange(3, device=nodes.device)
        rows = rows.permute(1, 0, 2, 3).reshape(K, -1)
        blocks = dense.transpose(0, 1).gather(1, rows.unsqueeze(-1).expand(-1, -1, O))
        first = torch.ones_like(rows, dtype=torch.bool)  # a neighbour that is the node itself (free end) counts once
        for i in range(1, rows.shape[1]):
            first[:, i] = (rows[:, :i] != rows[:, i:i + 1]).all(1)
        blocks = blocks * first.unsqueeze(-1)
        kept = torch.zeros(K, D, dtype=torch.bool, device=rows.device).scatter_(1, rows, True)
        if bool(dense.transpose(0, 1)[~kept].any()):
            raise RuntimeError("Input Layer I reads beyond a node's neighbours; freeze_features cannot split it")
        sign = self.mirror_sign.repeat(1, D // 3)  # (G, D)
        flip = (((frame[None, :, :, 0] + self.mirror_perm[:, None]) * 3)[..., None]
                + torch.arange(3, device=nodes.device)).flatten(1)  # (G, D)
        dense = dense.reshape(D, -1)
        return (torch.stack([s[:, None] * dense[f] for s, f in zip(sign, flip)], 1),
                torch.stack([f[rows] for f in flip]), torch.stack([s[rows].unsqueeze(-1) * blocks for s in sign]))

    def _stacked_lstm_weights(self) -> Tensor:
        """The LSTM's input and recurrent weights stacked, (F + hidden, 4 hidden): the right factor of
        ``[features, last output] @ W`` (:meth:`_lstm_last`)."""
        return torch.cat([self.lstm.weight_ih_l0, self.lstm.weight_hh_l0], 1).t()

    def _select_features(self) -> None:
        """The frozen matrices of the images in use, from every image's: views where the images in use are
        consecutive group elements (all of them, the first, the first two), so that a rollout entering and leaving
        :meth:`use_symmetry` copies nothing (the dense matrix is megabytes)."""
        if self._feature_matrix_group is None:
            return
        g = self.img_elements
        lo, n = int(g[0]), g.numel()
        if bool((g == torch.arange(lo, lo + n, device=g.device)).all()):
            pick = lambda t, dim: t.narrow(dim, lo, n)  # noqa: E731
        else:
            pick = lambda t, dim: t.index_select(dim, g)  # noqa: E731
        self._feature_matrix = pick(self._feature_matrix_group, 1).flatten(1)  # (D, G * K * W * F), image-major
        self._feature_rows, self._feature_blocks = pick(self._feature_rows_group, 0), pick(self._feature_blocks_group, 0)
        self._carry_rows, self._carry_blocks = pick(self._carry_rows_group, 0), pick(self._carry_blocks_group, 0)

    def unfreeze_features(self) -> None:
        self._feature_matrix = self._feature_rows = self._feature_blocks = self._carry_rows = self._carry_blocks = None
        self._feature_matrix_group = self._feature_rows_group = self._feature_blocks_group = None
        self._carry_rows_group = self._carry_blocks_group = None
        self._carry_wih = self._carry_whh = self._carry_bias = None
        self._head_w0 = self._head_b0 = None
        self._lstm_stacked = None

    def widen(self, head_hidden: int | None = None, stencil: int | None = None,
              mix: int | None = None) -> "NodeLSTMSurrogate":
        """A copy with a wider dense head (``head_hidden`` units per hidden layer, at least the current width),
        a wider stencil (``stencil``, at least the current one) and/or more rings of neighbours' LSTM outputs in
        the head (``mix``, at least the current) that steps exactly as this model does (net2net widening). The
        head's added units' incoming weights are drawn as a new layer's are, their outgoing weights are zero; the
        LSTM's weights on an added ring's features and the head's on added neighbours' outputs are zero. So
        nothing added changes an output until training moves it. For fine-tuning a model with more capacity
        (``train_surrogate.py --init-from`` with a larger ``--head-hidden``, ``--stencil`` or ``--mix``). An added ring's
        offset scales (``rel_scale[:, 6 * stencil:]``, ``stencil`` the current one) start at 1, which changes no
        step (its weights are zero); a training run sets them from its data first, as ``--init-from`` does."""
        c = self.config
        head_hidden = c.head_hidden if head_hidden is None else head_hidden
        stencil = c.stencil if stencil is None else stencil
        mix = c.mix if mix is None else mix
        if mix < c.mix:
            raise ValueError(f"mix must be >= the current mix {c.mix}, got {mix}")
        if head_hidden < c.head_hidden:
            raise ValueError(f"head_hidden must be >= the current width {c.head_hidden}, got {head_hidden}")
        if stencil < c.stencil:
            raise ValueError(f"stencil must be >= the current stencil {c.stencil}, got {stencil}")
        wide = NodeLSTMSurrogate(replace(c, head_hidden=head_hidden, mix=mix).with_stencil(stencil)
                                 ).to(self.length_scale.device)
        state = wide.state_dict()
        state["lstm.weight_ih_l0"][:, self.n_features:] = 0.0  # no input from the added ring
        state["head.0.weight"][:, self.head[0].in_features:] = 0.0  # none from the added neighbours' outputs
        for name, value in self.state_dict().items():
            if name.startswith("head.") and name.endswith(".weight") and name != "head.0.weight":
                state[name][:, c.head_hidden:] = 0.0  # no output from the added units
            state[name][tuple(slice(0, n) for n in value.shape)] = value
        wide.load_state_dict(state)
        return wide.train(self.training)

    def widened_to(self, config: NodeLSTMConfig, ring_scales: Tensor | None = None) -> "NodeLSTMSurrogate":
        """This model in the architecture ``config``, stepping as this model does: ``config`` may differ from this
        model's only in what has no weights (the chord projection, the rest anchor and its shape, the mirrors) and
        in a wider head, stencil or mix (:meth:`widen`, the neighbours' outputs then projected to its ``mix_width``
        by :meth:`with_mix_width`). Where a fine-tuning run (``train_surrogate.py --init-from``) grows a model, this
        is its starting point. An added ring's offset scales are taken from ``ring_scales`` (a ``rel_scale`` of
        ``config``'s stencil, e.g. from a run's data) where given, else they start at 1 (:meth:`widen`).
        ValueError naming both architectures otherwise."""
        c = self.config
        grown = replace(c, chord_projection=config.chord_projection, rest_anchor=config.rest_anchor,
                        rest_shape=config.rest_shape, reflections=config.reflections,
                        head_hidden=max(c.head_hidden, config.head_hidden), mix=max(c.mix, config.mix),
                        mix_width=config.mix_width).with_stencil(max(c.stencil, config.stencil))
        if grown != config:
            raise ValueError(f"architecture {c.to_dict()} does not grow into {config.to_dict()} (the same eta and "
                             "hidden, and a head, stencil and mix at least its own)")
        wide = self.widen(config.head_hidden, config.stencil, config.mix)
        if config.mix:
            wide = wide.with_mix_width(config.mix_width)
        out = NodeLSTMSurrogate(config).to(self.length_scale.device)
        out.load_state_dict(wide.state_dict())
        if ring_scales is not None:
            ring = 6 * c.stencil  # the offset scales this model holds; those after them are an added ring's
            with torch.no_grad():
                out.rel_scale[:, ring:] = ring_scales[:, ring:]
        return out.train(self.training)

    @property
    def _head_own_inputs(self) -> int:
        """The head's inputs before the neighbours' outputs: the node's own LSTM output, force features, embedding."""
        c = self.config
        return c.hidden + c.wrench_hidden + c.embedding

    def neighbour_weights(self) -> Tensor:
        """The head's first-layer weights on each mixed neighbour's whole LSTM output, (2 mix, head_hidden,
        hidden), slot by slot as :meth:`NodeLSTMConfig.mix_neighbours` (through the projection where
        ``mix_width``)."""
        c = self.config
        w = self.head[0].weight[:, self._head_own_inputs:].reshape(c.head_hidden, 2 * c.mix, -1).transpose(0, 1)
        return w if self.mix_proj is None else w @ self.mix_proj.weight

    @torch.no_grad()
    def with_mix_width(self, width: int) -> "NodeLSTMSurrogate":
        """A copy whose head sees each mixed neighbour's LSTM output through a shared linear projection to
        ``width`` numbers (0: the whole output), its weights the best rank-``width`` approximation (least squares)
        of this model's weights on the neighbours' outputs taken together (:meth:`neighbour_weights`): the
        projection their leading right singular vectors. Exact (to round-off) where ``width`` is 0 or at least this
        model's (``hidden`` where it has none), so ``--init-from`` can narrow or keep a trained mixing head."""
        c = self.config
        if c.mix == 0:
            raise ValueError("with_mix_width: the model has no mixing head (mix 0) whose inputs to project")
        config = replace(c, mix_width=width)  # checks the width
        if width == c.mix_width:
            return copy.deepcopy(self)
        out = NodeLSTMSurrogate(config).to(self.length_scale.device)
        state = {k: v for k, v in self.state_dict().items() if not k.startswith(("head.0.", "mix_proj."))}
        full, n0 = self.neighbour_weights(), self._head_own_inputs  # (2 mix, head_hidden, hidden)
        if width:
            proj = torch.linalg.svd(full.flatten(0, 1), full_matrices=False)[2][:width]  # (width, hidden)
            state["mix_proj.weight"], full = proj, full @ proj.t()
        state["head.0.weight"] = torch.cat([self.head[0].weight[:, :n0], full.transpose(0, 1).flatten(1)], 1)
        state["head.0.bias"] = self.head[0].bias
        out.load_state_dict(state)
        return out.train(self.training)

    def train(self, mode: bool = True):
        if mode:
            self.unfreeze_features()
            if self.symmetry_axes:
                self.use_symmetry(())
        return super().train(mode)

    def _lstm_last(self, f: Tensor, program: bool = False, stacked: bool | None = None) -> Tensor:
        """The LSTM's last output for (S, W, F) from the zero state, as its gate equations (the first
        recurrent product vanishes): for compiled programs, where it beats the decomposed ``nn.LSTM``, and
        training (the frames unbound, not indexed: the backward stacks instead of filling zeros per frame).
        ``program``: with the activations of :func:`_program_sigmoid` and :func:`_program_tanh`. ``stacked`` (by
        default in the program form): each frame's features and the last output in one product against both
        weight matrices, instead of all frames' input product first (``python scripts/bench/surrogate_program.py``,
        two runs: 6-9 % less time for the compiled four-image Simulation III step, within +-2 us with one or two)."""
        lstm = self.lstm
        sigmoid, tanh = (_program_sigmoid, _program_tanh) if program else (torch.sigmoid, torch.tanh)
        bias = lstm.bias_ih_l0 + lstm.bias_hh_l0
        if stacked is None:
            stacked = program
        if stacked:
            both = self._stacked_lstm_weights() if self._lstm_stacked is None else self._lstm_stacked
            frames = f.unbind(1)

            def gates(x: Tensor, h: Tensor | None) -> Tensor:
                return (x @ lstm.weight_ih_l0.t() if h is None else torch.cat([x, h], -1) @ both) + bias
        else:
            frames = (f @ lstm.weight_ih_l0.t() + bias).unbind(1)

            def gates(x: Tensor, h: Tensor | None) -> Tensor:
                return x if h is None else x + h @ lstm.weight_hh_l0.t()
        h = c = None
        for x in frames:
            g = gates(x, h)
            i, fg, gg, o = g.chunk(4, -1)
            i, gg, o = sigmoid(i), tanh(gg), sigmoid(o)
            c = i * gg if c is None else sigmoid(fg) * c + i * gg
            h = o * tanh(c)
        return h

    def _input_features(self, hist: Tensor, ref: Tensor, program: bool) -> Tensor:
        """Input Layer I of every symmetry image ``g`` in use of the inputs, as (G * B * K, W, F) LSTM
        sequences (image-major; frozen, the reflections are folded into the feature matrices)."""
        B, W = hist.shape[:2]
        M = self._feature_matrix
        if M is None:
            return self.features(*self._frame_images(hist, ref)).reshape(-1, W, self.n_features)
        x = torch.cat([hist, ref[:, None]], 1).reshape(B, -1)
        if program:
            f = torch.einsum("bgki,gkio->gbko", x[:, self._feature_rows], self._feature_blocks)
        else:
            f = (x @ M).reshape(B, self.img_sign.shape[0], -1).transpose(0, 1)
        return f.reshape(-1, W, self.n_features)

    def _frame_images(self, hist: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
        """Every symmetry image in use of frames (B, W, n_tracked, 3) and the reference (B, n_tracked, 3), as
        (G * B, W, n_tracked, 3) and (G * B, n_tracked, 3), image-major."""
        if self.img_sign.shape[0] == 1:
            return hist, ref
        images = (hist[:, :, self.img_perm] * self.img_sign[:, None]).movedim(2, 0).flatten(0, 1)
        return images, self._mirror_images(ref)

    def _mirror_images(self, x: Tensor) -> Tensor:
        """Every symmetry image in use ``g x`` of frames (B, n_tracked, 3), as (G * B, n_tracked, 3),
        image-major."""
        return (x[:, self.img_perm] * self.img_sign[:, None]).movedim(1, 0).flatten(0, 1)

    def _accel(self, hist: Tensor, wrench: Tensor, ref: Tensor, program: bool) -> Tensor:
        """The head's second difference (B, K, 3) in metres, symmetrised over the mirror group, before the
        rest anchor."""
        f = self._input_features(hist, ref, program)
        if program:
            h = self._lstm_last(f, program=True)
        else:
            h = self._lstm_last(f) if self.training else self.lstm(f)[0][:, -1]
        return self._image_heads(h, wrench, program)

    def _image_heads(self, h: Tensor, wrench: Tensor, program: bool) -> Tensor:
        """The second difference (B, K, 3) in metres, symmetrised over the mirror group, from every image's LSTM
        outputs (G * B * K, hidden), image-major, and the forces (B, K, 3)."""
        if self.mirror_sign.shape[0] == 1:
            return self._head(h, wrench, program)
        S, pk = self.img_sign[:, None], self.img_perm_modeled
        a = self._head(h, (wrench[:, pk] * S).movedim(1, 0).flatten(0, 1), program)
        return self._mean_back(a, wrench.shape[0])

    def _head(self, h: Tensor, wrench: Tensor, program: bool) -> Tensor:
        """Second difference (B, K, 3) in metres from the LSTM's last outputs (B * K, hidden) and the forces
        (B, K, 3): the force layers, the node embedding and the dense head."""
        B, K = wrench.shape[:2]
        mlp, linear = (_program_mlp, _program_linear) if program else (nn.Module.__call__, nn.Module.__call__)
        folded = program and self._head_w0 is not None  # the embedding and the last force layer in the head's first
        wf = mlp(self.wrench[:-1] if folded else self.wrench, wrench / self.f_scale)
        h = h.reshape(B, K, -1)
        parts = [h, wf] if folded else [h, wf, self.embed.weight.expand(B, K, -1)]
        if self.idx_mix is not None:  # the neighbours' (projected) LSTM outputs, zero for none
            n = h if self.mix_proj is None else linear(self.mix_proj, h)
            if self._mix_shifts is None:
                parts.append(nn.functional.pad(n, (0, 0, 0, 1))[:, self.idx_mix].reshape(B, K, -1))
            else:  # the same as slices of the zero-padded outputs: no gather in a compiled program
                r = max(abs(d) for d in self._mix_shifts)
                n = nn.functional.pad(n, (0, 0, r, r))
                parts += [n[:, r + d:r + d + K] for d in self._mix_shifts]
        x = torch.cat(parts, -1)
        if folded:
            return mlp(self.head[1:], x @ self._head_w0 + self._head_b0) * self.a_scale
        return mlp(self.head, x) * self.a_scale

    def _folded_first_layer(self) -> tuple[Tensor, Tensor]:
        """The head's first layer with the node embedding folded into a bias per node and the force layers' last
        (linear) layer into its weights: its weights on the LSTM output, the force layers' hidden output and the
        neighbours', transposed, (inputs - embedding, head_hidden), and the bias (K, head_hidden) (:meth:`_head` in
        a compiled program; frozen by :meth:`freeze_features`)."""
        w, last, n0, n2 = self.head[0].weight, self.wrench[-1], self.config.hidden, self._head_own_inputs
        n1 = n0 + self.config.wrench_hidden
        w_force, w_embed = w[:, n0:n1], w[:, n1:n2]
        weights = torch.cat([w[:, :n0], w_force @ last.weight, w[:, n2:]], 1).t()
        return weights, self.head[0].bias + last.bias @ w_force.t() + self.embed.weight @ w_embed.t()

    def rest_accel(self, ref: Tensor, program: bool = False) -> Tensor:
        """The head's output (B, K, 3) at rest: every history frame the reference shape (B, n_tracked, 3),
        or the config's ``rest_shape`` where given, no force. What ``rest_anchor`` subtracts; constant along
        a rollout, so compute it once and pass it to :meth:`forward` as ``rest``."""
        W, K = self.config.eta + 1, self.idx_modeled.numel()
        still = ref if self.rest_frame is None else self.rest_frame.to(ref.dtype).expand_as(ref)
        hist = still[:, None].expand(-1, W, -1, -1)
        return self._accel(hist, ref.new_zeros(ref.shape[0], K, 3), ref, program)

    def forward(self, hist: Tensor, wrench: Tensor, ref: Tensor, program: bool = False,
                rest: Tensor | None = None) -> Tensor:
        """One surrogate step: history (B, eta+1, n_tracked, 3), node forces (B, K, 3) and the reference
        shape (B, n_tracked, 3) -> the modelled nodes' next positions (B, K, 3). ``program``: the same
        function in the form that compiles best (frozen features per node, the LSTM as its gate
        equations), slower eagerly. ``rest``: :meth:`rest_accel` of ``ref`` where the model is
        ``rest_anchor``ed (computed here when not given; ignored otherwise)."""
        self.check_inputs(hist, ref, wrench)
        a = self._accel(hist, wrench, ref, program)
        if self.config.rest_anchor:
            a = a - (self.rest_accel(ref, program) if rest is None else rest)
        pk = hist[:, -1, self.idx_modeled]
        return 2 * pk - hist[:, -2, self.idx_modeled] + a

    def check_inputs(self, hist: Tensor, ref: Tensor, wrench: Tensor | None = None) -> None:
        """ValueError naming the first of a step's inputs whose shape is not the model's: the history (B, eta+1,
        n_tracked, 3) (one of another length would step silently wrong: the LSTM runs any length), the reference
        shape (B, n_tracked, 3) and the modelled nodes' forces (B, K, 3); then the first whose dtype is not the
        model's. A few us: the eager step checks every call, a compiled program only when it is traced."""
        c, B = self.config, hist.shape[0] if hist.dim() else "B"
        dtype = self.a_scale.dtype
        for name, x, legend, shape in (
                ("hist", hist, "(B, eta + 1, n_tracked, 3)", (B, c.eta + 1, c.n_tracked, 3)),
                ("ref", ref, "(B, n_tracked, 3)", (B, c.n_tracked, 3)),
                ("wrench", wrench, "(B, K modelled nodes, 3)", (B, len(c.modeled), 3))):
            if x is not None and tuple(x.shape) != shape:
                raise ValueError(f"{name} must be {legend} = {shape}, got {tuple(x.shape)}")
        for name, x in (("hist", hist), ("ref", ref), ("wrench", wrench)):
            if x is not None and x.dtype != dtype:
                raise ValueError(f"{name} must be {dtype} (the model's dtype), got {x.dtype}")

    def _newest_features(self, frames: Tensor, ref: Tensor) -> Tensor:
        """Input Layer I (B, K, F) of the newest of two frames (B, 2, n_tracked, 3), as a window's LSTM sees it at
        any position but the first (where its step is zero, :meth:`features`)."""
        return self.features(frames, ref)[:, :, 1]

    def _carried_weights(self) -> tuple[Tensor, Tensor, Tensor]:
        """The LSTM's input and recurrent weights, transposed, and its summed biases, (F, 4 hidden), (hidden, 4 hidden),
        (4 hidden,), with the cell gate's doubled, so that one sigmoid serves all four gates (the cell gate's tanh(x)
        as 2 sigmoid(2x) - 1): :meth:`carried_step`'s, frozen as constants by :meth:`freeze_features` (with a sigmoid
        and a tanh per gate, or the scales multiplied inside the program, the compiled two-image Simulation III step
        took 86-87 us instead of 75)."""
        lstm, scale = self.lstm, self._gate_scale
        return lstm.weight_ih_l0.t() * scale, lstm.weight_hh_l0.t() * scale, (lstm.bias_ih_l0 + lstm.bias_hh_l0) * scale

    def carried_step(self, h: Tensor, c: Tensor, frames: Tensor, wrench: Tensor, ref: Tensor, rest: Tensor,
                     program: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:meth:`forward` with each window's LSTM states carried from the step before, for a rollout at inference
        (the images in use fixed throughout; :class:`cmlearn.surrogate.Stepper` drives it). A window's LSTM state at
        a position depends only on the frames up to it, so each step runs its newest frame once at each of the
        ``eta + 1`` positions (its Input Layer I once, one recurrent product for all positions) instead of running
        the whole window: the same step to float round-off in fewer operations.

        ``h, c`` (eta + 1, G * B * K, hidden), position-major, image-major within: the states after the last frame
        but one at each position of a window (the last position unused); ``frames`` (B, 2, n_tracked, 3) the last two
        frames; ``rest`` (B, K, 3) what is subtracted from the head's output (zero, or a rest anchor's output at rest
        in this same arithmetic). Returns the next positions (B, K, 3), the second difference (B, K, 3) they add, and
        the states after the last frame."""
        B, E = frames.shape[0], self.config.eta
        if self._carry_blocks is not None:
            x = torch.cat([frames, ref[:, None]], 1).reshape(B, -1)
            f = torch.einsum("bgki,gkio->gbko", x[:, self._carry_rows], self._carry_blocks)
        else:
            f = self._newest_features(*self._frame_images(frames, ref))
        f = f.reshape(1, -1, self.n_features)  # (1, G * B * K, F)
        sigmoid, tanh = (_program_sigmoid, _program_tanh) if program else (torch.sigmoid, torch.tanh)
        w_ih, w_hh, bias = self._carried_weights() if self._carry_wih is None else \
            (self._carry_wih, self._carry_whh, self._carry_bias)
        p = f @ w_ih + bias
        # at a window's first position its step (STEP_FEATURES) is zero: its product taken out, as a sum over 3
        first = p - (f[..., STEP_FEATURES, None] * w_ih[STEP_FEATURES]).sum(-2)
        s = sigmoid(torch.cat([first, p + h[:E] @ w_hh]))  # (eta + 1, G * B * K, 4 hidden)
        i, fg, gg, o = s.chunk(4, -1)
        c = i * (2 * gg - 1) + fg * nn.functional.pad(c[:E], (0, 0, 0, 0, 1, 0))  # a window starts at zero
        h = o * tanh(c)
        a = self._image_heads(h[E], wrench, program) - rest
        return 2 * frames[:, 1, self.idx_modeled] - frames[:, 0, self.idx_modeled] + a, a, h, c

    def project_chords(self, frame: Tensor, ref: Tensor, iters: int = 2) -> Tensor:
        """``frame`` (B, n_tracked, 3) with the modelled nodes moved, anchors fixed, so that every chord between
        consecutive tracked nodes has its length in ``ref`` (B, n_tracked, 3): ``iters`` Gauss-Newton steps
        ``x -= J^T (J J^T)^-1 g`` for the chord errors ``g`` (``J J^T`` is tridiagonal along the chain), each
        the smallest move that fixes the chords to first order, so the result is the nearest such frame up to
        terms quadratic in the chord errors. Differentiable. With mirror symmetries it is the mean of the projections
        of every mirror image, mapped back (``x + mean_g g^-1 (P(g x) - g x)``, the moves being translation free):
        the projections of a frame and of its image round differently, and the mean takes no side."""
        if self.mirror_sign.shape[0] == 1:
            return self._project_chords(frame, ref, iters)
        images = self._mirror_images(frame)
        return frame + self._mean_back(self._project_chords(images, self._mirror_images(ref), iters) - images,
                                       frame.shape[0], modeled=False)

    def _project_chords(self, frame: Tensor, ref: Tensor, iters: int) -> Tensor:
        target = (ref[:, 1:] - ref[:, :-1]).norm(dim=-1)
        m = self.movable
        both = m[:-1] + m[1:]  # a chord between two anchors cannot change: its row is left out
        pinned = both == 0
        for _ in range(iters):
            d = frame[:, 1:] - frame[:, :-1]
            length = d.norm(dim=-1)
            u = d / length.unsqueeze(-1)
            g = (length - target).masked_fill(pinned, 0.0)
            off = -m[1:-1] * (u[:, :-1] * u[:, 1:]).sum(-1)
            A = torch.diag_embed(both.masked_fill(pinned, 1.0).expand_as(g)) + torch.diag_embed(off, 1) \
                + torch.diag_embed(off, -1)
            lam_u = torch.linalg.solve(A, g.unsqueeze(-1)) * u  # (B, C, 3)
            pad = lam_u.new_zeros(lam_u.shape[0], 1, 3)
            frame = frame - m[:, None] * (torch.cat([pad, lam_u], 1) - torch.cat([lam_u, pad], 1))
        return frame

    def rollout(self, hist: Tensor, wrench: Tensor, ref: Tensor, anchors: Tensor | None = None,
                wrench_fn=None) -> Tensor:
        """Free-running rollout of H steps from ``hist`` (B, eta+1, n_tracked, 3) with node forces ``wrench``
        (B, H, K, 3) and reference shape ``ref`` (B, n_tracked, 3); anchor nodes follow ``anchors``
        (B, H, n_tracked, 3) where given, else stay put. ``wrench_fn(h, frame) -> (B, K, 3)``, where given,
        replaces ``wrench[:, h]`` by forces computed from the last frame (closed loop). With ``chord_projection``
        each new frame is :meth:`project_chords`-ed. Returns
        (B, H, n_tracked, 3)."""
        W = self.config.eta + 1
        if hist.shape[1] != W:
            raise ValueError(f"hist must hold eta + 1 = {W} frames, got {hist.shape[1]}")
        H = wrench.shape[1] if wrench.dim() > 1 else 0
        if H < 1:
            raise ValueError(f"wrench must hold at least one step (B, H >= 1, K, 3), got {tuple(wrench.shape)}")
        if anchors is not None and (anchors.dim() != 4 or anchors.shape[1] < H
                                    or anchors.shape[::2] != hist.shape[::2] or anchors.shape[-1] != 3):
            raise ValueError(f"anchors must be (B, H, n_tracked, 3) = ({hist.shape[0]}, {H}, {hist.shape[2]}, 3), "
                             f"got {tuple(anchors.shape)}")
        frames = list(hist.unbind(1))
        rest = self.rest_accel(ref) if self.config.rest_anchor else None
        out = []
        for h in range(H):
            nxt = anchors[:, h] if anchors is not None else frames[-1]
            w = wrench[:, h] if wrench_fn is None else wrench_fn(h, frames[-1])
            pk = self(torch.stack(frames[-W:], 1), w, ref, rest=rest)
            nxt = nxt.index_copy(1, self.idx_modeled, pk)
            if self.config.chord_projection:
                nxt = self.project_chords(nxt, ref)
            frames.append(nxt)
            out.append(nxt)
        return torch.stack(out, 1)
