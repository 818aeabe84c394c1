"""cmlearn: learning and control for magnetically actuated continuum manipulators.

Physics lives in the ``physics`` package (torch only); ``cmlearn`` adds data, surrogates, PINNs,
reinforcement learning, evaluation and the ``cmlearn`` command line (:mod:`cmlearn.cli`).
Importing this package is deliberately light: submodules load their heavy dependencies lazily.
"""
__version__ = "0.1.0"

__all__ = ["__version__"]
