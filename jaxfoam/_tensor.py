"""Small-tensor algebra on components (structure of arrays).

A matrix is a tuple of rows of components; each component is an array of the batch shape (...)
or a Python number (a known constant, e.g. the plane-strain zeros and ones). Operations unroll at
trace time into elementwise code: XLA:CPU runs that several times faster than batched 3x3
`dot_general` or reductions over axes of length 3 (shared/perf/anchors.md), and constants fold away.
"""
from __future__ import annotations

import jax.numpy as jnp


def _is_const(a, value):
    return isinstance(a, (int, float)) and a == value


def mul(a, b):
    if _is_const(a, 0) or _is_const(b, 0):
        return 0.0
    if _is_const(a, 1):
        return b
    if _is_const(b, 1):
        return a
    return a * b


def add(a, b):
    if _is_const(a, 0):
        return b
    if _is_const(b, 0):
        return a
    return a + b


def sub(a, b):
    if _is_const(b, 0):
        return a
    if _is_const(a, 0):
        return -b
    return a - b


def comps(a, pad_to: int | None = None):
    """(..., r, c) array -> components; pad_to=3 embeds a d x d block in the 3x3 identity."""
    r, c = a.shape[-2], a.shape[-1]
    n = pad_to or r
    return tuple(tuple(a[..., i, j] if (i < r and j < c) else (1.0 if i == j else 0.0) for j in range(n))
                 for i in range(n))


def array(M, like):
    """Components -> (..., r, c) array with the batch shape and dtype of `like` (an array).

    Written component by component into a zero array, not stacked: XLA:CPU fuses a concatenate's
    producers into it and recomputes them per output component (docs/performance.md).
    """
    out = jnp.zeros(like.shape + (len(M), len(M[0])), like.dtype)
    for i, row in enumerate(M):
        for j, m in enumerate(row):
            out = out.at[..., i, j].set(jnp.broadcast_to(jnp.asarray(m, like.dtype), like.shape))
    return out


def block(M, d):
    """The upper-left d x d block."""
    return tuple(tuple(M[i][j] for j in range(d)) for i in range(d))


def matmul(A, B):
    n, k, p = len(A), len(B), len(B[0])
    out = []
    for i in range(n):
        row = []
        for j in range(p):
            acc = 0.0
            for l in range(k):
                acc = add(acc, mul(A[i][l], B[l][j]))
            row.append(acc)
        out.append(tuple(row))
    return tuple(out)


def transpose(A):
    return tuple(tuple(A[j][i] for j in range(len(A))) for i in range(len(A[0])))


def scale(A, s):
    return tuple(tuple(mul(a, s) for a in row) for row in A)


def madd(A, B):
    return tuple(tuple(add(a, b) for a, b in zip(ra, rb)) for ra, rb in zip(A, B))


def trace(A):
    acc = 0.0
    for i in range(len(A)):
        acc = add(acc, A[i][i])
    return acc


def det(A):
    n = len(A)
    if n == 2:
        return sub(mul(A[0][0], A[1][1]), mul(A[0][1], A[1][0]))
    if n == 3:
        c0 = sub(mul(A[1][1], A[2][2]), mul(A[1][2], A[2][1]))
        c1 = sub(mul(A[1][0], A[2][2]), mul(A[1][2], A[2][0]))
        c2 = sub(mul(A[1][0], A[2][1]), mul(A[1][1], A[2][0]))
        return add(sub(mul(A[0][0], c0), mul(A[0][1], c1)), mul(A[0][2], c2))
    raise ValueError(f"dimension must be 2 or 3, got {n}")


def add_diag(A, s):
    """A + s I."""
    return tuple(tuple(add(a, s) if i == j else a for j, a in enumerate(row)) for i, row in enumerate(A))


def dev(A):
    """A - tr(A)/3 I (3x3)."""
    return add_diag(A, mul(-1.0 / 3.0, trace(A)))


def where(pred, A, B):
    """Componentwise jnp.where(pred, A, B); an entry that is the same constant in both stays a constant."""
    return tuple(tuple(a if (isinstance(a, (int, float)) and isinstance(b, (int, float)) and a == b)
                       else jnp.where(pred, a, b) for a, b in zip(ra, rb)) for ra, rb in zip(A, B))


def frob_sq(A):
    acc = 0.0
    for row in A:
        for a in row:
            acc = add(acc, mul(a, a))
    return acc
