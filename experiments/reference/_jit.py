"""numba.njit when numba is installed (the `reference` extra), else the plain Python function.

Every kernel of the reference simulator is written in the subset of Python that numba compiles, so
the same code runs compiled (fast) or interpreted (slow, for tiny test problems) without change.
Set REFSIM_NO_NUMBA=1 to force the interpreted path.
"""
from __future__ import annotations

import os

try:
    if os.environ.get("REFSIM_NO_NUMBA"):
        raise ImportError("REFSIM_NO_NUMBA set")
    import numba

    HAVE_NUMBA = True

    def kernel(fn):
        """Compile fn with numba (cached on disk beside this package)."""
        return numba.njit(cache=True, fastmath=False)(fn)
except ImportError:
    HAVE_NUMBA = False

    def kernel(fn):
        """numba is missing: run fn as plain Python."""
        return fn
