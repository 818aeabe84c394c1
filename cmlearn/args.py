"""Command-line options of the training scripts declared once, as a dataclass: each field's default, type,
``--help`` text, choices and bounds make its flag (``--train-seed`` for ``train_seed``; a ``bool`` field a switch).
:func:`bounded` is the same checked number type for the scripts' plain argparse options."""
from __future__ import annotations

import argparse
import math
from dataclasses import field, fields

__all__ = ["opt", "dataclass_parser", "bounded"]


def opt(default, help: str, choices=None, at_least=None, above=None):
    """A dataclass field whose ``help`` is the argument's ``--help`` text, ``choices`` its valid values and
    ``at_least`` / ``above`` its lower bound (inclusive / exclusive), checked as the command line is parsed."""
    return field(default=default, metadata={"help": help, "choices": choices, "at_least": at_least, "above": above})


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
        ap.add_argument(flag, type=kind, default=f.default, help=meta["help"], choices=meta["choices"])
    return ap
