"""Atomic file writes (a reader never sees a half-written dataset, checkpoint, table or figure) and the
error every checkpoint loader raises."""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

__all__ = ["atomic_write", "write_text_atomic", "save_torch_atomic", "check_writable", "CheckpointError",
           "weights_digest", "header_digest", "seal", "check_digests", "save_sealed"]


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable or truncated, of another format or architecture, or for
    another task."""


def weights_digest(state_dict: dict) -> str:
    """SHA-256 of a state dict's names, dtypes, shapes and values (a checkpoint stores it as ``weights_sha256``)."""
    import torch
    h = hashlib.sha256()
    for k in sorted(state_dict):
        v = state_dict[k].detach().cpu().contiguous()
        h.update(f"{k}:{v.dtype}:{tuple(v.shape)};".encode())
        h.update(v.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


_DIGESTS = ("weights_sha256", "header_sha256")


def header_digest(blob: dict) -> str:
    """SHA-256 of everything in a checkpoint but its weights and digests (format, configuration, metadata), as
    key-sorted JSON (a checkpoint stores it as ``header_sha256``)."""
    rest = {k: v for k, v in blob.items() if k != "state_dict" and k not in _DIGESTS}
    return hashlib.sha256(json.dumps(rest, sort_keys=True, default=str).encode()).hexdigest()


def seal(blob: dict) -> dict:
    """``blob`` (a checkpoint's dict with its ``state_dict``) with the digests of its weights and of the rest added."""
    return {**blob, "weights_sha256": weights_digest(blob["state_dict"]), "header_sha256": header_digest(blob)}


def check_digests(path: str | Path, blob: dict) -> None:
    """:class:`CheckpointError` where a checkpoint's weights, or its configuration and metadata, differ from the
    digests stored with them (a corrupt file whose archive still reads). A checkpoint without a digest passes that
    check: the weights' digest came on 2026-12-02, the header's on 2026-12-04."""
    want = blob.get("weights_sha256")
    if want is not None and weights_digest(blob.get("state_dict", {})) != want:
        raise CheckpointError(f"{path}: the weights do not match their stored SHA-256: the file is corrupt")
    want = blob.get("header_sha256")
    if want is not None and header_digest(blob) != want:
        raise CheckpointError(f"{path}: the configuration or metadata do not match their stored SHA-256: the file "
                              "is corrupt")


def check_writable(path: str | Path, folder: bool = False) -> Path:
    """``path`` (a file, or with ``folder`` a folder) as a :class:`~pathlib.Path` if it can be written there,
    checked before a long run so that it does not fail only at its end; otherwise :class:`ValueError` saying why.
    Nothing is left behind: a temporary file is made and removed in the nearest folder that exists, which a
    missing folder would be made in."""
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise ValueError(f"{str(path)!r} is a file, not a folder")
    if not folder and path.is_dir():
        raise ValueError(f"{str(path)!r} is a folder, not a file")
    near = path if folder else path.parent
    while not near.exists() and near != near.parent:
        near = near.parent
    if not near.is_dir():
        raise ValueError(f"cannot write {str(path)!r}: {str(near)!r} is a file, not a folder")
    try:
        fd, tmp = tempfile.mkstemp(dir=near, prefix=".cmlearn-write-check.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise ValueError(f"cannot write {str(path)!r}: {e.strerror or e} in {str(near)!r}") from None
    return path


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(file)`` on a temporary file next to ``path`` (binary mode), flush it to disk, then rename it into
    place (and flush the folder's entry), so that neither a crash nor a power loss leaves a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_folder(path.parent)
    return path


def _fsync_folder(folder: Path) -> None:
    """Flush a folder's entries to disk (the rename); a no-op where the platform cannot open folders."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_text_atomic(path: str | Path, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text.encode()))


def save_torch_atomic(path: str | Path, obj) -> Path:
    """``torch.save(obj)`` to ``path`` atomically."""
    import torch
    return atomic_write(path, lambda f: torch.save(obj, f))


def save_sealed(path: str | Path, blob: dict) -> Path:
    """:func:`seal` ``blob`` and save it to ``path``, and its plain-JSON ``"meta"`` beside it as ``<name>.json``, each
    atomically; a ValueError where ``path`` itself ends in .json (the metadata overwrote the weights just written)."""
    path = Path(path)
    if path.suffix == ".json":
        raise ValueError(f"path must not end in .json (the metadata goes to <name>.json), got {str(path)!r}")
    if "meta" not in blob:  # a KeyError came after the weights were written, and left them without their .json
        raise ValueError(f"blob must carry its metadata under 'meta', got keys {sorted(blob)}")
    text = json.dumps(blob["meta"], indent=2, default=str) + "\n"
    save_torch_atomic(path, seal(blob))
    write_text_atomic(path.with_suffix(".json"), text)
    return path
