"""Surrogate against physics on a recorded trajectory: one-step and free-running errors.

The trajectory's first frame is the surrogate's reference shape.

``evaluate(model, task, positions, wrench, start)`` compares, for the task's nodes of interest,

* one-step: each prediction made from the true history (the thesis's evaluation), and
* free-running: the surrogate rolled out from the true history at frame ``start`` on its own
  predictions to the end,

(``node_recursive``, a diagnostic between the two: the node of interest alone runs on its own predictions,
every other tracked node comes from the recorded trajectory, as each of Paper II's per-node models sees
its neighbours' measured poses)

and returns per-axis max/mean absolute errors (mm, % of L) and RMSE(t) (II.2).
"""
from __future__ import annotations

import re

import torch
from torch import Tensor

from cmlearn.eval.metrics import axis_errors, rmse_t

__all__ = ["used_seeds", "one_step", "node_recursive", "free_running", "evaluate", "evaluate_scenes", "from_rest",
           "interest_slots", "fresh_errors", "fresh_score", "metric_lines", "THESIS_ERRORS_MM", "thesis_errors"]

# Paper II's errors of the node of interest, (max, mean) absolute error in mm per axis x, y, z
THESIS_ERRORS_MM = {
    "ellipse": ((1.57, 0.27), (2.27, 0.46), (0.23, 0.06)),
    "ellipse_horizontal": ((26.33, 3.37), (21.71, 3.70), (4.92, 4.22)),
    "square_tracking": ((3.58, 1.70), (1.80, 0.69), (2.73, 1.41)),
    "square_tracking_heldout": ((10.49, 2.61), (5.54, 1.05), (5.97, 2.83)),
    "semicircle": ((1.36, 0.78), (0.23, 0.13), (2.22, 0.81)),
    "semicircle_heldout": ((3.73, 1.25), (2.0, 0.2), (8.1, 1.2)),
}


def thesis_errors(task: str, case: str):
    """Paper II's figures for a case of a checkpoint's metrics (``"seen_last40"`` or a held-out scene of ``task``),
    or ``None`` where the thesis gives none."""
    if case == "seen_last40":
        return THESIS_ERRORS_MM.get(task)
    return THESIS_ERRORS_MM.get(case) or THESIS_ERRORS_MM.get(f"{task}_heldout")


def interest_slots(task, scene) -> list[int]:
    """Tracked-list positions of the scene's nodes of interest that the task models."""
    pos = {n: i for i, n in enumerate(task.tracked)}
    return [pos[n] for n in scene.nodes_of_interest if n in pos]


def from_rest(positions: Tensor, wrench: Tensor, eta: int) -> tuple[Tensor, Tensor]:
    """A trajectory from rest with ``eta`` copies of its first frame (and zero wrench) before it, so that
    the surrogate's rollout from frame ``eta`` starts from rest: ``free_running(model, *from_rest(p, W,
    eta), eta)``."""
    return (torch.cat([positions[:1].expand(eta, *positions.shape[1:]), positions], 0),
            torch.cat([wrench.new_zeros(eta, *wrench.shape[1:]), wrench], 0))


def heldout_case(task, name: str, eta: int, duration: float | None = None,
                 data_dir=None) -> tuple[Tensor, Tensor, float]:
    """A held-out scene of ``task`` simulated by the LGVI (for ``duration`` if given; cached in ``data_dir`` if
    given, :func:`cmlearn.data.reference_rollout`), as the modelled nodes' wrench and the tracked positions from
    rest (``from_rest``), with the LGVI wall time."""
    from cmlearn.data import reference_rollout
    from cmlearn.data.windows import node_wrench
    p, W, wall = reference_rollout(task, name, duration, data_dir)
    return (*from_rest(p, node_wrench(W.float(), task.wrench_nodes, task.modeled), eta), wall)


def _check_case(positions: Tensor, wrench: Tensor, start: int) -> None:
    """ValueError naming the input where ``wrench`` is not the T-1 intervals of ``positions`` (T, ...) or no frame
    follows ``start``."""
    T = positions.shape[0]
    if wrench.shape[0] != T - 1:
        raise ValueError(f"wrench must hold the T - 1 = {T - 1} intervals of positions {tuple(positions.shape)}, "
                         f"got {tuple(wrench.shape)}")
    if not start < T - 1:
        raise ValueError(f"start must be < T - 1 = {T - 1} (a frame to predict after it), got {start}")


@torch.no_grad()
def one_step(model, positions: Tensor, wrench: Tensor, start: int) -> Tensor:
    """Teacher-forced predictions of frames start+1 .. T-1: (T-1-start, n_tracked, 3)."""
    _check_case(positions, wrench, start)
    W = model.config.eta + 1
    t = torch.arange(max(start, W - 1), positions.shape[0] - 1)
    hist = torch.stack([positions[t - W + 1 + j] for j in range(W)], 1)
    ref = positions[:1].float().expand(len(t), -1, -1)
    pk = model(hist.float(), wrench[t].float(), ref)
    out = positions[t + 1].clone().float()
    out[:, model.idx_modeled] = pk
    return out


@torch.no_grad()
def node_recursive(model, positions: Tensor, wrench: Tensor, start: int, slot: int) -> Tensor:
    """Predictions (T-1-start, 3) of tracked node ``slot`` for frames start+1 .. T-1, each from a history in
    which that node holds its own earlier predictions (the true ones up to ``start``) and every other
    tracked node its recorded positions. The node must be modelled. The network's step alone: a model's chord
    projection, which moves every node at once, is not applied."""
    hit = (model.idx_modeled == slot).nonzero()
    if hit.numel() != 1:
        raise ValueError(f"slot {slot} is not a modelled node of this surrogate")
    k, W = int(hit), model.config.eta + 1
    _check_case(positions, wrench, start)
    if start < W - 1:
        raise ValueError(f"start must be >= eta = {W - 1}")
    own = list(positions[start - W + 1:start + 1, slot].float().unbind(0))
    ref = positions[:1].float()
    for t in range(start, positions.shape[0] - 1):
        hist = positions[t - W + 1:t + 1].float().clone()
        hist[:, slot] = torch.stack(own[-W:])
        own.append(model(hist[None], wrench[t].float()[None], ref)[0, k])
    return torch.stack(own[W:])


@torch.no_grad()
def free_running(model, positions: Tensor, wrench: Tensor, start: int) -> Tensor:
    """Free-running predictions of frames start+1 .. T-1 from the true history ending at ``start``."""
    _check_case(positions, wrench, start)
    W = model.config.eta + 1
    if start < W - 1:
        raise ValueError(f"start must be >= eta = {W - 1}")
    hist = positions[start - W + 1:start + 1].float()[None]
    anchors = positions[start + 1:].float()[None]
    return model.rollout(hist, wrench[start:].float()[None], positions[:1].float(), anchors=anchors)[0]


def evaluate(model, positions: Tensor, wrench: Tensor, start: int, slots, length: float) -> dict:
    """Errors of both modes at the tracked ``slots`` (the first is the headline node)."""
    W = model.config.eta + 1
    s = max(start, W - 1)
    ref = positions[s + 1:, slots].double()
    out = {}
    for mode, fn in (("one_step", one_step), ("free_running", free_running)):
        pred = fn(model, positions, wrench, s)[:, slots].double()
        r = rmse_t(pred[:, 0], ref[:, 0])
        out[mode] = {"node": axis_errors(pred[:, 0], ref[:, 0], length),
                     "all_nodes_max_mm": float((pred - ref).abs().max()) * 1e3,
                     "rmse_mean_mm": float(r.mean()) * 1e3, "rmse_max_mm": float(r.max()) * 1e3}
    return out


@torch.no_grad()
def fresh_errors(model, task, data: dict) -> list[dict]:
    """Free-running errors (:func:`cmlearn.eval.metrics.axis_errors`) of the node of interest on each variant of
    ``data`` but the first (the printed scene), each from rest, all variants in one batched rollout on the model's
    device. ``data``: a dataset of ``task`` (:func:`cmlearn.data.cached_dataset`), for instance fresh variants that
    no model was trained on."""
    from cmlearn.data.windows import node_wrench
    meta, eta = data["meta"], model.config.eta
    dev = model.length_scale.device
    slot = interest_slots(task, task.base_scene())[0]
    wrench = node_wrench(data["wrench"], meta["wrench_nodes"], meta["modeled"]).float()
    starts = [from_rest(p, w, eta) for p, w in zip(data["positions"][1:].float(), wrench[1:])]
    pos, wr = torch.stack([p for p, _ in starts]).to(dev), torch.stack([w for _, w in starts]).to(dev)
    pred = model.rollout(pos[:, :eta + 1], wr[:, eta:], pos[:, 0], anchors=pos[:, eta + 1:]).cpu()
    ref = pos[:, eta + 1:].cpu()
    return [axis_errors(pred[v, :, slot].double(), ref[v, :, slot].double(), meta["rod_length"])
            for v in range(pred.shape[0])]


def used_seeds(meta: dict) -> dict[int, str]:
    """The variant seeds a checkpoint or any model it was made from trained on or was selected by (``{seed: how}``),
    from its metadata: its data seed, its fresh validation seed, a refinement's or a blend's selection seed, and the
    ``--seed``/``--val-seed`` of the commands in its provenance (``init_from``, a blend's ends). Fresh variants that
    rank or score it must be drawn with another seed."""
    used = {}
    if meta.get("data_seed") is not None:
        used[int(meta["data_seed"])] = "its variants were trained on"
    args = meta.get("args", {})
    if args.get("val_fresh") and args.get("val_seed") is not None:
        used.setdefault(int(args["val_seed"]), "it drew the validation variants that selected it")
    for what, sel in (("its refinement", (meta.get("refine") or {}).get("select")),
                      ("its blend", (meta.get("blend") or {}).get("fresh"))):
        if isinstance(sel, dict) and sel.get("seed") is not None:
            used.setdefault(int(sel["seed"]), f"it drew the variants that selected {what}")
    blend = meta.get("blend") or {}
    for src in (meta.get("init_from"), blend.get("start"), blend.get("end")):
        cmd = src.get("command", "") if isinstance(src, dict) else ""
        for flag, how in (("--val-seed", "a model it was made from was selected by"),
                          ("--seed", "a model it was made from was trained on")):
            for seed in re.findall(rf"{flag}[ =](\d+)", cmd):
                used.setdefault(int(seed), how)
    return used


def fresh_score(errors: list[dict]) -> float:
    """Mean over the variants of :func:`fresh_errors` of the largest axis's max error (mm)."""
    return sum(max(e[ax]["max_mm"] for ax in "xyz") for e in errors) / len(errors)


def metric_lines(metrics: dict, modes=("one_step", "free_running")) -> list[str]:
    """One line per case of :func:`evaluate_scenes`'s ``metrics`` and mode: the node of interest's max/mean error
    per axis (mm), as the training and refinement scripts print them."""
    return [f"  {case:28s} {mode:12s} " + "  ".join(
        f"{ax}: {m[mode]['node'][ax]['max_mm']:.2f}/{m[mode]['node'][ax]['mean_mm']:.2f} mm" for ax in "xyz")
        for case, m in metrics.items() for mode in modes]


def evaluate_scenes(model, task, data: dict, duration: float | None = None, data_dir=None) -> dict:
    """:func:`evaluate` on the printed scene (``data``'s variant 0 from its test cut, the last 40 %) as
    ``"seen_last40"`` and on each held-out scene of ``task`` from rest (the LGVI's run, :func:`heldout_case`, with
    its wall time as ``lgvi_wall_s``), keyed by scene name. Position tasks only (the magnetic rod has its own)."""
    from cmlearn.data.windows import node_wrench, split_ranges
    meta = data["meta"]
    pos = data["positions"][0]
    wr = node_wrench(data["wrench"][0], meta["wrench_nodes"], meta["modeled"])
    scene = task.base_scene()
    L = scene.rod.length
    cut = split_ranges(meta["n_variants"], pos.shape[0])["test"][0][1]
    metrics = {"seen_last40": evaluate(model, pos, wr, cut, interest_slots(task, scene), L)}
    eta = model.config.eta
    for name in task.heldout:
        p, Wk, wall = heldout_case(task, name, eta, duration, data_dir)
        metrics[name] = evaluate(model, p, Wk, eta, interest_slots(task, task.scene_by_name(name)), L)
        metrics[name]["lgvi_wall_s"] = wall
    return metrics


def short_check(engine, scene_name: str, duration: float, data_dir=None) -> dict:
    """Free-running surrogate against the LGVI on the first ``duration`` seconds of a scene: the
    headline node's maximum error (mm). Shipped with each checkpoint so that a test can reproduce it. The
    LGVI's run is cached in ``data_dir`` if given (:func:`cmlearn.data.reference_rollout`)."""
    from dataclasses import replace

    from cmlearn.data.generate import reference_rollout

    task = engine.task
    if task.custom:
        return task.hook("short_check")(engine, scene_name, duration, data_dir)
    scene = replace(task.scene_by_name(scene_name), duration=duration)
    ref, _, _ = reference_rollout(task, scene_name, duration, data_dir)
    pred, _ = engine.run_scene(scene)
    slot = interest_slots(task, scene)[0]
    return {"scene": scene_name, "duration": duration,
            "max_err_mm": float((pred[:, slot].double() - ref[:, slot].double()).abs().max()) * 1e3}


def recorded_check(model, meta: dict, duration: float | None = None, data_dir=None) -> dict:
    """The :func:`short_check` a checkpoint records, for ``model`` with metadata ``meta``: 50 surrogate steps of
    the task's printed scene (at most ``duration`` seconds), short enough that even an unstable rollout is
    reproducible bit for bit; ``{"diverged": message}`` (and a warning) where the rollout runs away, so that the
    checkpoint is still written for study but cannot pass as a shipped one."""
    import sys

    from cmlearn.surrogate.engine import Surrogate, SurrogateDivergence
    engine = Surrogate(model, meta)
    try:
        return short_check(engine, engine.task.scene, min(50 * engine.task.delta, duration or 1.0), data_dir)
    except SurrogateDivergence as e:
        print(f"warning: {e}", file=sys.stderr)
        return {"diverged": str(e)}
