"""The old import paths of the calibration package's modules, kept for one release."""
import importlib
import warnings


def alias(old: str, new: str, modules: tuple):
    """Warn that jaxfoam.<old> is deprecated for <new>; return the module's (__getattr__, __dir__), which
    look every name up in `modules` in turn."""
    warnings.warn(f"jaxfoam.{old} is deprecated: import {new} instead (the same names)", DeprecationWarning,
                  stacklevel=3)

    def __getattr__(name):
        for module in modules:
            module = importlib.import_module(module)
            if hasattr(module, name):
                return getattr(module, name)
        raise AttributeError(f"module 'jaxfoam.{old}' has no attribute {name!r}")

    def __dir__():
        return sorted({n for m in modules for n in dir(importlib.import_module(m)) if not n.startswith("__")})

    return __getattr__, __dir__
