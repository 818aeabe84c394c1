"""Atomic file writes (a reader never sees a half-written dataset, checkpoint, table or figure) and the
error every checkpoint loader raises."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

__all__ = ["atomic_write", "write_text_atomic", "save_torch_atomic", "CheckpointError"]


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable or truncated, of another format or architecture, or for
    another task."""


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(file)`` on a temporary file next to ``path`` (binary mode), then rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text.encode()))


def save_torch_atomic(path: str | Path, obj) -> Path:
    """``torch.save(obj)`` to ``path`` atomically."""
    import torch
    return atomic_write(path, lambda f: torch.save(obj, f))
