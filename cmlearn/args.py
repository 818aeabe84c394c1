"""Command-line options of the training scripts declared once, as a dataclass: each field's default, type,
``--help`` text, choices and bounds make its flag (``--train-seed`` for ``train_seed``; a ``bool`` field a switch).
:func:`bounded` is the same checked number type for the scripts' plain argparse options."""
from __future__ import annotations

import argparse
import math
from dataclasses import field, fields
from pathlib import Path

__all__ = ["opt", "dataclass_parser", "bounded", "writable", "readable"]


def opt(default, help: str, choices=None, at_least=None, above=None, path: str | None = None):
    """A dataclass field whose ``help`` is the argument's ``--help`` text, ``choices`` its valid values,
    ``at_least`` / ``above`` its lower bound (inclusive / exclusive) and ``path`` ("file", "folder" or
    "checkpoint": an output the run writes, :func:`writable`; "input": a file it reads, :func:`readable`), checked as
    the command line is parsed."""
    return field(default=default, metadata={"help": help, "choices": choices, "at_least": at_least, "above": above,
                                            "path": path})


def bounded(kind, at_least=None, above=None):
    """An argparse ``type``: ``kind`` (int or float) of the text, finite for a float, within the bounds
    (``at_least`` inclusive, ``above`` exclusive); otherwise argparse's error naming the flag."""
    def convert(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {'an integer' if kind is int else 'a number'}, got {text!r}")
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
        if at_least is not None and not value >= at_least:
            raise argparse.ArgumentTypeError(f"must be >= {at_least}, got {text!r}")
        if above is not None and not value > above:
            raise argparse.ArgumentTypeError(f"must be > {above}, got {text!r}")
        return value
    return convert


def writable(folder: bool = False, kind=str, checkpoint: bool = False):
    """An argparse ``type``: an output file (or ``folder``) the run will write, as ``kind`` of the text, checked
    by :func:`cmlearn.io.check_writable` as the command line is parsed (before hours of training end in an
    unwritable path); the empty text (the script's default path) passes unchecked. ``checkpoint``: weights whose
    metadata go beside them as ``<name>.json`` (:func:`cmlearn.io.save_sealed`), so not a name ending in .json."""
    def convert(text: str):
        if checkpoint and text.endswith(".json"):
            raise argparse.ArgumentTypeError(f"must not end in .json (the metadata goes to <name>.json), got {text!r}")
        if text:
            from .io import check_writable
            try:
                check_writable(text, folder)
            except ValueError as e:
                raise argparse.ArgumentTypeError(str(e)) from None
        return kind(text)
    return convert


def readable(kind=str):
    """An argparse ``type``: a file the run will read (a checkpoint to resume or start from), as ``kind`` of the
    text, which must exist when the command line is parsed (not only once the data are generated); the empty text
    (none) passes."""
    def convert(text: str):
        if text and not Path(text).is_file():
            raise argparse.ArgumentTypeError(f"no such file: {text!r}")
        return kind(text)
    return convert


def dataclass_parser(cls, description: str) -> argparse.ArgumentParser:
    """An argument parser with one flag per field of the dataclass ``cls`` (fields made by :func:`opt`)."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for f in fields(cls):
        flag, meta = f"--{f.name.replace('_', '-')}", f.metadata
        if f.type in ("bool", bool):
            ap.add_argument(flag, action="store_true", help=meta["help"])
            continue
        kind = type(f.default)
        if kind in (int, float):
            kind = bounded(kind, meta.get("at_least"), meta.get("above"))
        elif meta.get("path") == "input":
            kind = readable()
        elif meta.get("path"):
            kind = writable(meta["path"] == "folder", checkpoint=meta["path"] == "checkpoint")
        ap.add_argument(flag, type=kind, default=f.default, help=meta["help"], choices=meta["choices"])
    return ap
