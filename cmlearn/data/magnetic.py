"""Data of the magnetic-rod surrogate (Paper II, Data-set IV): tracked points, magnet frames, wrench inputs.

The surrogate sees points, not rotations, so each magnet block is tracked by four points: the two
rod nodes at its ends (``a``, ``b``) and two virtual markers rigidly attached to the block,
``c + MARKER_OFFSET R e1`` (lateral) and ``c + MARKER_OFFSET R e3`` (axial), with ``c`` the block centre
and ``R`` its rotation in the LGVI (``R_a cay(psi / 2)``). Their ids in a task's node lists are
``n_nodes + 2k`` and ``n_nodes + 2k + 1`` for magnet ``k``. From the points the block frame is rebuilt
as ``e3`` the axial marker's direction from the centre ``(p_a + p_b) / 2``, ``e1`` the lateral one's
with its e3 part removed, ``e2 = e3 x e1`` (:func:`magnet_frames`); on the LGVI's trajectories this
is the block rotation to round-off. The 20 mm lever arms make a surrogate's point error of 0.1 mm an
orientation error of 0.3 deg (a 1 mm arm would make it 6 deg).

Input wrench. The field's torque ``tau = m x B`` and force ``f = grad(m . B)`` on each magnet (``m`` along
the rebuilt e3, field and gradient of the exact eMNS at the centre, currents at the middle of the step)
enter the node model as the statically equivalent forces on the block's end nodes::

    f_a = f / 2 - tau x d / |d|^2,   f_b = f / 2 + tau x d / |d|^2,   d = p_b - p_a

which carry [tau, f] exactly (``tau`` is normal to an axial moment, so ``tau = d x (f_b - f_a) / 2`` and
``f = f_a + f_b``). The wrench of step k -> k+1 is a function of frame k and the currents at
``(k + 1/2) delta`` alone, so a free-running surrogate computes it from its own last prediction.
Closed-loop training does the same in the field expanded to first order about the recorded block
centres (:func:`field_samples`, :func:`linearised_field`), which is cheap and differentiable; the
evaluation uses the exact field.
"""
from __future__ import annotations

import functools
from dataclasses import replace

import torch
from torch import Tensor

from physics.coil_currents import CoilField
from physics.elastic import relative_cayley
from physics.loads import magnet_poses

__all__ = ["MARKER_OFFSET", "marker_ids", "tracked_points", "magnet_frames", "magnet_wrench", "wrench_inputs",
           "by_frames", "equivalent_forces", "field_samples", "linearised_field",
           "rollout", "simulate", "block_nodes"]

MARKER_OFFSET = 20e-3  # m: lever arm of the virtual markers


@functools.cache
def block_nodes(rod) -> tuple[tuple[int, int], ...]:
    """End nodes (a, b) of the element of each magnet (cached per rod: a traced closed loop reads it as a
    constant)."""
    return tuple((e, e + 1) for e, _ in rod.magnet_weights())


def marker_ids(rod) -> list[tuple[int, int]]:
    """(lateral, axial) marker ids of each magnet."""
    return [(rod.n_nodes + 2 * k, rod.n_nodes + 2 * k + 1) for k in range(len(rod.magnets))]


def _slots(task, rod):
    pos = {n: i for i, n in enumerate(task.tracked)}
    try:
        ab = [(pos[a], pos[b]) for a, b in block_nodes(rod)]
        mk = [(pos[m1], pos[m3]) for m1, m3 in marker_ids(rod)]
    except KeyError as e:
        raise ValueError(f"task {task.name!r} must track both end nodes and the marker of every magnet "
                         f"(missing {e.args[0]})") from None
    return ab, mk


def tracked_points(task, rod, p: Tensor, R: Tensor) -> Tensor:
    """Tracked points (..., n_tracked, 3) of LGVI frames ``p`` (..., n, 3), ``R`` (..., n, 3, 3)."""
    prm = rod.params(p.dtype, p.device)
    centre, Rm, _ = magnet_poses(p, R, relative_cayley(R, check=False), prm)
    markers = centre[..., :, None, :] + MARKER_OFFSET * Rm[..., :, :, [0, 2]].transpose(-1, -2)  # (..., K, 2, 3)
    n = rod.n_nodes
    cols = [p[..., i, :] if i < n else markers[..., (i - n) // 2, (i - n) % 2, :] for i in task.tracked]
    return torch.stack(cols, -2)


def magnet_frames(task, rod, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Block centres (..., K, 3), rotations (..., K, 3, 3) and end-node chords (..., K, 3) from tracked points."""
    ab, mk = _slots(task, rod)
    pa = points[..., [a for a, _ in ab], :]
    pb = points[..., [b for _, b in ab], :]
    d = pb - pa
    c = 0.5 * (pa + pb)
    e3 = points[..., [m3 for _, m3 in mk], :] - c
    e3 = e3 / e3.norm(dim=-1, keepdim=True)
    u = points[..., [m1 for m1, _ in mk], :] - c
    u = u - (u * e3).sum(-1, keepdim=True) * e3
    e1 = u / u.norm(dim=-1, keepdim=True)
    e2 = torch.linalg.cross(e3, e1, dim=-1)
    return c, torch.stack((e1, e2, e3), -1), d


def check_tracked_points(task, rod, points: Tensor, name: str = "positions") -> None:
    """ValueError unless ``points`` (..., n_tracked, 3) are finite tracked points of ``task`` (:func:`tracked_points`):
    each magnet's markers at :data:`MARKER_OFFSET` (within 10 %) from its block's centre (node positions of the
    same count would give frames of 0/0)."""
    n = len(task.tracked)
    if not torch.is_tensor(points) or points.shape[-2:] != (n, 3) or not bool(torch.isfinite(points).all()):
        raise ValueError(f"{name} must be finite tracked points (..., {n}, 3) of task {task.name!r}, got "
                         f"{tuple(points.shape) if torch.is_tensor(points) else type(points).__name__}")
    ab, mk = _slots(task, rod)
    c = 0.5 * (points[..., [a for a, _ in ab], :] + points[..., [b for _, b in ab], :])
    arms = torch.stack([(points[..., list(pair), :] - c[..., k:k + 1, :]).norm(dim=-1)
                        for k, pair in enumerate(mk)], -2)
    worst = float((arms / MARKER_OFFSET - 1).abs().max())
    if worst > 0.1:
        raise ValueError(f"{name} are not tracked points of task {task.name!r}: a magnet's marker lies "
                         f"{worst:.0%} off its {MARKER_OFFSET * 1e3:g} mm lever arm (node positions? use "
                         "tracked_points)")


def magnet_wrench(emns, centre: Tensor, R: Tensor, moments: Tensor, currents: Tensor):
    """Force and torque (..., K, 3) on magnets of body moments ``moments`` (K, 3) at ``centre`` with
    rotation ``R``, in ``emns`` driven by ``currents`` (..., C) (exact coil superposition)."""
    return _dipole_wrench(R, moments, *emns.field_and_gradient(centre, currents.to(centre.dtype)))


def _dipole_wrench(R: Tensor, moments: Tensor, B: Tensor, dB: Tensor):
    m = (R * moments.to(R.dtype)[:, None, :]).sum(-1)
    return (dB * m[..., :, None]).sum(-2), torch.linalg.cross(m, B, dim=-1)


def equivalent_forces(task, rod, points: Tensor, field) -> Tensor:
    """Node forces (..., n_wrench, 3) in ``task.wrench_nodes`` order from frames ``points`` (..., n_tracked, 3)
    and ``field(centres) -> (B, dB)`` at the magnet block centres (..., K, 3) (module docstring)."""
    c, R, d = magnet_frames(task, rod, points)
    moments = torch.tensor([mg.moment for mg in rod.magnets], dtype=points.dtype, device=points.device)
    f, tau = _dipole_wrench(R, moments, *field(c))
    couple = torch.linalg.cross(tau, d, dim=-1) / (d * d).sum(-1, keepdim=True)
    fa, fb = 0.5 * f - couple, 0.5 * f + couple
    by_node = {}
    for k, (a, b) in enumerate(block_nodes(rod)):
        by_node[a] = by_node.get(a, 0) + fa[..., k, :]
        by_node[b] = by_node.get(b, 0) + fb[..., k, :]
    return torch.stack([by_node[n] for n in task.wrench_nodes], -2)


def wrench_inputs(task, rod, emns, points: Tensor, currents: Tensor) -> Tensor:
    """Node forces (..., n_wrench, 3) in ``task.wrench_nodes`` order, from frames ``points`` (..., n_tracked, 3)
    and currents (..., C), with the exact eMNS field (module docstring)."""
    return equivalent_forces(task, rod, points, lambda c: emns.field_and_gradient(c, currents.to(c.dtype)))


def field_samples(task, rod, emns, points: Tensor, currents: Tensor) -> Tensor:
    """The field along trajectories, for :func:`linearised_field`: (..., K, 15) = the block centres, ``B`` and
    ``dB_i/dx_j`` (flattened) at them, from frames ``points`` (..., n_tracked, 3) and currents (..., C)."""
    c = magnet_frames(task, rod, points)[0]
    B, dB = emns.field_and_gradient(c, currents.to(c.dtype))
    return torch.cat([c, B, dB.flatten(-2)], -1)


def linearised_field(samples: Tensor):
    """``field(c) -> (B, dB)`` expanded to first order about :func:`field_samples` ``samples`` (..., K, 15):
    ``B(c) = B0 + dB0 (c - c0)`` and ``dB(c) = dB0`` (as :class:`physics.coil_currents.CoilField` does
    within its 0.2 mm tolerance); cheap and differentiable, for training rollouts that compute their own
    wrench near a recorded trajectory."""
    c0, B0, dB0 = samples[..., :3], samples[..., 3:6], samples[..., 6:].unflatten(-1, (3, 3))
    return lambda c: (B0 + (dB0 @ (c - c0)[..., None])[..., 0], dB0)


def by_frames(fn, points: Tensor, currents: Tensor, chunk: int = 256) -> Tensor:
    """``fn(points, currents)`` (:func:`wrench_inputs`, :func:`field_samples`) on frames (..., T, n_tracked, 3)
    and currents (..., T, C), ``chunk`` frames at a time, joined along T: the coil field of every frame of a
    dataset at once takes gigabytes (8 GB for 32 profiles of 1,200 frames)."""
    return torch.cat([fn(points[..., s:s + chunk, :, :], currents[..., s:s + chunk, :])
                      for s in range(0, points.shape[-3], chunk)], -3)


def currents_series(currents, n: int, delta: float, offset: float = 0.5) -> Tensor:
    """Currents at ``(k + offset) delta``, k = 0..n-1: (n, ..., C) stacked along a new first axis."""
    return torch.stack([torch.as_tensor(currents(torch.tensor((k + offset) * delta, dtype=torch.float64)))
                        for k in range(n)])


def rollout(task, scene, currents=None, duration: float | None = None, compile: bool = False):
    """LGVI run of ``scene`` (optionally with other ``currents(t) -> (C,) or (V, C)``): tracked points
    (..., T, n_tracked, 3) every ``task.delta``, wrench inputs (..., T-1, n_wrench, 3) and the wall time. ``compile``:
    the LGVI's compiled rollout (:func:`cmlearn.data.generate.lgvi_frames`; the wall time leaves its compile out)."""
    from .generate import lgvi_frames
    field = scene.loads.field
    cur = field.currents if currents is None else currents
    scene = replace(scene, loads=replace(scene.loads, field=CoilField(field.emns, cur, field.tol)),
                    duration=duration or scene.duration)
    task.check_duration(scene.duration)
    n_frames = int(round(scene.duration / task.delta)) + 1
    sim = scene.make_integrator()
    cfg = scene.initial_configuration()
    I0 = torch.as_tensor(cur(torch.tensor(0.0, dtype=torch.float64)))
    p, R = cfg["p"], cfg["R"]
    if I0.dim() == 2:
        p, R = p.expand(I0.shape[0], -1, -1), R.expand(I0.shape[0], -1, -1, -1)
    every = task.record_every(scene)
    P, Rs, wall, _ = lgvi_frames(sim, sim.initial_state(p=p, R=R), n_frames, every, compile, record_R=True)
    pts = tracked_points(task, scene.rod, P, Rs)
    I = currents_series(cur, n_frames - 1, task.delta).movedim(0, -2)  # (..., T-1, C)
    W = by_frames(lambda p, i: wrench_inputs(task, scene.rod, field.emns, p, i), pts[..., :-1, :, :], I)
    return pts, W, wall


def simulate(task, n_variants: int, seed: int = 0, duration: float | None = None):
    """``n_variants`` current profiles of the task's scene (variant 0 the printed one) as one LGVI batch;
    returns what :func:`cmlearn.data.generate.simulate_task` does."""
    scene = task.base_scene()
    if duration:
        scene = replace(scene, duration=duration)
    var = task.variants(scene, n_variants, seed)
    pts, W, wall = rollout(task, scene, currents=var["currents"])
    return pts, W, var["info"], wall
