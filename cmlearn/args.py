"""Command-line options of the training scripts declared once, as a dataclass: each field's default, type,
``--help`` text and choices make its flag (``--train-seed`` for ``train_seed``; a ``bool`` field a switch)."""
from __future__ import annotations

import argparse
from dataclasses import field, fields

__all__ = ["opt", "dataclass_parser"]


def opt(default, help: str, choices=None):
    """A dataclass field whose ``help`` is the argument's ``--help`` text (and ``choices`` its valid values)."""
    return field(default=default, metadata={"help": help, "choices": choices})


def dataclass_parser(cls, description: str) -> argparse.ArgumentParser:
    """An argument parser with one flag per field of the dataclass ``cls`` (fields made by :func:`opt`)."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for f in fields(cls):
        flag, help = f"--{f.name.replace('_', '-')}", f.metadata["help"]
        if f.type in ("bool", bool):
            ap.add_argument(flag, action="store_true", help=help)
        else:
            ap.add_argument(flag, type=type(f.default), default=f.default, help=help, choices=f.metadata["choices"])
    return ap
