"""Deprecated alias of `fitting.track` (moved with the calibration package); removed in the next release."""
import importlib
import warnings

warnings.warn("jaxfoam.track is deprecated: import fitting.track instead (the same names)", DeprecationWarning, stacklevel=2)

_MODULES = ('fitting.track', 'fitting.video', 'fitting.cli')


def __getattr__(name):
    for module in _MODULES:
        module = importlib.import_module(module)
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module 'jaxfoam.track' has no attribute {name!r}")


def __dir__():
    return sorted({n for m in _MODULES for n in dir(importlib.import_module(m)) if not n.startswith("__")})
