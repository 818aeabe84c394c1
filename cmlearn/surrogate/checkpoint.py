"""Surrogate checkpoints: weights plus metadata, written atomically, loadable without Lightning.

A checkpoint is a ``torch.save`` dict::

    {"format": "cmlearn-surrogate/1", "model_class": "NodeLSTMSurrogate", "config": {...},
     "state_dict": {...}, "weights_sha256": "...", "header_sha256": "...",
     "meta": {"task", "scene", "data_hash", "metrics", "command", "version", ...}}

(the digests of the weights and of everything else, :func:`cmlearn.io.seal`, checked on load)

with a JSON copy of ``meta`` next to it (``<name>.json``) for humans and tools.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

from cmlearn.data.tasks import TASKS
from cmlearn.io import CheckpointError, check_digests, save_sealed
from cmlearn.models import NodeLSTMConfig, NodeLSTMSurrogate

__all__ = ["FORMAT", "CheckpointError", "save_checkpoint", "read_blob", "load_checkpoint", "surrogate_checkpoints", "provenance"]

FORMAT = "cmlearn-surrogate/1"
_CLASSES = {"NodeLSTMSurrogate": (NodeLSTMSurrogate, NodeLSTMConfig)}


def plain_meta(meta: dict) -> dict:
    """``meta`` as plain JSON types (loadable with ``weights_only=True``); a ValueError where its ``"task"`` names
    no surrogate task, which every loader needs (the checkpoint was written and then could not be loaded)."""
    if not isinstance(meta, dict) or meta.get("task") not in TASKS:
        raise ValueError(f"meta must be a dict whose 'task' is one of {sorted(TASKS)}, got task "
                         f"{meta.get('task') if isinstance(meta, dict) else type(meta).__name__!r}")
    return json.loads(json.dumps(meta, default=str))


def save_checkpoint(path: str | Path, model: NodeLSTMSurrogate, meta: dict) -> Path:
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    return save_sealed(path, {"format": FORMAT, "model_class": type(model).__name__,
                              "config": model.config.to_dict(), "state_dict": state, "meta": plain_meta(meta)})


def read_blob(path: str | Path, fmt: str, task: str | None = None) -> tuple[dict, dict]:
    """The dict a checkpoint of format ``fmt`` holds, and its metadata, loaded on the CPU with
    ``weights_only``; :class:`CheckpointError` for a missing, unreadable or truncated file, another format,
    weights that differ from their stored digest, or (``task`` given) another task."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means an unusable file
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {str(e)[:200]})") from None
    if not isinstance(blob, dict) or blob.get("format") != fmt:
        raise CheckpointError(f"{path}: not a {fmt} checkpoint")
    check_digests(path, blob)
    meta = blob.get("meta", {})
    if not isinstance(meta, dict) or meta.get("task") not in TASKS:
        raise CheckpointError(f"{path}: its metadata names no surrogate task (got "
                              f"{meta.get('task') if isinstance(meta, dict) else meta!r})")
    if task is not None and meta.get("task") != task:
        raise CheckpointError(f"{path}: checkpoint is for task {meta.get('task')!r}, not {task!r}")
    return blob, meta


def load_checkpoint(path: str | Path, task: str | None = None) -> tuple[NodeLSTMSurrogate, dict]:
    """The model (eval mode, float32, CPU) and its metadata; :class:`CheckpointError` on any problem."""
    blob, meta = read_blob(path, FORMAT, task)
    cls = _CLASSES.get(blob.get("model_class"))
    if cls is None:
        raise CheckpointError(f"{path}: unknown model class {blob.get('model_class')!r}")
    if not isinstance(blob.get("config"), dict):
        raise CheckpointError(f"{path}: no model configuration (a 'config' dict), got "
                              f"{type(blob.get('config')).__name__}")
    try:
        cfg = dict(blob["config"])
        for key in ("modeled", "left", "right", "left2", "right2", "left3", "right3"):
            if cfg.get(key) is not None:
                cfg[key] = tuple(cfg[key])
        if "mirror_axis" in cfg:  # a one-reflection checkpoint from before the symmetry groups (2026-11-25)
            axis, nodes = cfg.pop("mirror_axis"), cfg.pop("mirror_nodes", None)
            cfg["reflections"] = () if axis is None else ((axis, nodes),)
        if cfg.get("rest_shape") is not None:
            cfg["rest_shape"] = tuple(tuple(float(x) for x in r) for r in cfg["rest_shape"])
        cfg["reflections"] = tuple((int(a), None if m is None else tuple(m)) for a, m in cfg.get("reflections", ()))
        model = cls[0](cls[1](**cfg))
        model.load_state_dict(blob["state_dict"])
    except (TypeError, ValueError, RuntimeError, KeyError) as e:
        raise CheckpointError(f"{path}: weights do not match the stored configuration ({str(e)[:200]})") from None
    return model.eval(), meta


def provenance(path: str | Path, meta: dict) -> dict:
    """What a checkpoint made from the checkpoint at ``path`` (metadata ``meta``) records as its ``init_from``: the
    file's path and SHA-256, and the command and data hash that made it."""
    return {"path": str(path), "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
            "command": meta.get("command"), "data_hash": meta.get("data_hash")}


def surrogate_checkpoints(folder: str | Path) -> list[Path]:
    """The node-surrogate checkpoints in ``folder`` (those whose JSON metadata names a task and no other format;
    the folder also holds the agent's and the quasi-static hybrid's)."""
    out = []
    for p in sorted(Path(folder).glob("*.pt")):
        meta = p.with_suffix(".json")
        if meta.is_file():
            m = json.loads(meta.read_text())
            if "task" in m and m.get("format", FORMAT) == FORMAT:
                out.append(p)
    return out
