"""Deprecated alias of `fitting.synth` (moved with the calibration package); removed in the next release."""
import importlib
import warnings

warnings.warn("jaxfoam.synth is deprecated: import fitting.synth instead (the same names)", DeprecationWarning, stacklevel=2)

_MODULES = ('fitting.synth', 'fitting.cli')


def __getattr__(name):
    for module in _MODULES:
        module = importlib.import_module(module)
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module 'jaxfoam.synth' has no attribute {name!r}")


def __dir__():
    return sorted({n for m in _MODULES for n in dir(importlib.import_module(m)) if not n.startswith("__")})
