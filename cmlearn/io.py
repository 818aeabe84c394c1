"""Atomic file writes (a reader never sees a half-written dataset, checkpoint, table or figure) and the
error every checkpoint loader raises."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

__all__ = ["atomic_write", "write_text_atomic", "save_torch_atomic", "CheckpointError", "weights_digest",
           "check_weights"]


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable or truncated, of another format or architecture, or for
    another task."""


def weights_digest(state_dict: dict) -> str:
    """SHA-256 of a state dict's names, dtypes, shapes and values (a checkpoint stores it as ``weights_sha256``)."""
    import hashlib

    import torch
    h = hashlib.sha256()
    for k in sorted(state_dict):
        v = state_dict[k].detach().cpu().contiguous()
        h.update(f"{k}:{v.dtype}:{tuple(v.shape)};".encode())
        h.update(v.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def check_weights(path: str | Path, blob: dict) -> None:
    """:class:`CheckpointError` where a checkpoint's weights differ from the digest stored with them (a corrupt
    file whose archive still reads); checkpoints without one (written before 2026-12-02) pass."""
    want = blob.get("weights_sha256")
    if want is not None and weights_digest(blob.get("state_dict", {})) != want:
        raise CheckpointError(f"{path}: the weights do not match their stored SHA-256: the file is corrupt")


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
