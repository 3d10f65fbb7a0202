"""A multi-start as a population: the starts run together and their evaluations are batched.

Each start runs the ordinary driver (`least_squares`, `minimize`) in its own thread; the oracle every
start calls is a `BatchOracle`, which holds a request until every running start has asked for its
next point, then evaluates them all in one call of a batched function and hands each start its
result. Every start therefore follows exactly the path it would follow alone (the batched function
must equal the single one row by row); what changes is that a step of S starts costs one batched
evaluation instead of S.
"""
from __future__ import annotations

import threading
from typing import Callable

import numpy as np


class PopulationStopped(Exception):
    """Raised in a start's thread when another start of the population failed (the fit stops)."""


class BatchOracle:
    """Batches the evaluation requests of concurrently running starts.

    Args:
      evaluate_batch: X (B, p) -> a pytree of arrays with leading axis B (for least squares, (R (B, n),
        J (B, n, p))), row b the evaluation at X[b].
      workers: the number of starts that will call it (each calls `leave` when it ends).
      sizes: batch sizes the batched function is called with, ascending (a compiled program per size);
        a batch of k requests is padded to the smallest size >= k by repeating its last point (those
        results are dropped). None: the exact number of requests.
    Attributes:
      calls: batched calls made; rows: points evaluated (padding excluded); padded: padding rows.
    """

    def __init__(self, evaluate_batch: Callable, workers: int, sizes=None):
        self.evaluate_batch = evaluate_batch
        self.live = int(workers)
        self.sizes = None if sizes is None else sorted(int(s) for s in sizes)
        self._cv = threading.Condition()
        self._local = threading.local()
        self._pending: list = []
        self._results: dict = {}
        self.error: BaseException | None = None
        self.calls = self.rows = self.padded = 0

    def bind(self, index: int) -> None:
        """Name the calling thread's start (its rows then come in start order in every batch, as a batch
        split over several processes needs)."""
        self._local.index = int(index)

    def __call__(self, x):
        """Evaluate at x (p,), batched with the other running starts' requests; blocks until done."""
        with self._cv:
            if self.error is not None:
                raise PopulationStopped("another start of the population failed") from self.error
            key = (getattr(self._local, "index", 0), object())
            self._pending.append((key, np.asarray(x)))
            self._run_if_ready()
            while key not in self._results:
                self._cv.wait()
            out = self._results.pop(key)
        if isinstance(out, BaseException):
            raise PopulationStopped("the batched evaluation failed") from out
        return out

    def leave(self, error: BaseException | None = None) -> None:
        """A start ended (with `error` if it raised one: the population then stops)."""
        with self._cv:
            self.live -= 1
            if error is not None and self.error is None and not isinstance(error, PopulationStopped):
                self.error = error
            self._run_if_ready()

    def _size_for(self, k: int) -> int:
        if self.sizes is None:
            return k
        return next((s for s in self.sizes if s >= k), k)

    def _run_if_ready(self):
        # Called with the lock held: every running start is waiting, so the batch is complete.
        if not self._pending or len(self._pending) < self.live:
            return
        batch, self._pending = sorted(self._pending, key=lambda item: item[0][0]), []
        X = np.stack([x for _, x in batch])
        k = len(batch)
        size = self._size_for(k)
        if size > k:
            X = np.concatenate([X, np.repeat(X[-1:], size - k, axis=0)])
        try:
            out = self.evaluate_batch(X)
            rows = [_row(out, i) for i in range(k)]
        except BaseException as exc:  # every waiting start sees it
            rows = [exc] * k
        self.calls += 1
        self.rows += k
        self.padded += size - k
        for (key, _), row in zip(batch, rows):
            self._results[key] = row
        self._cv.notify_all()


def _row(tree, i):
    if isinstance(tree, (tuple, list)):
        return type(tree)(_row(t, i) for t in tree)
    return tree[i]


def run_population(solve: Callable, starts, oracle: BatchOracle, **kwargs) -> list:
    """`solve(x0, run=i, **kwargs)` for every start i, each in its own thread, all calling `oracle`.

    Returns the solutions in start order; the first exception a start raised (other than the
    `PopulationStopped` it causes in the others) is raised after every thread has ended."""
    starts = np.asarray(starts)
    out: list = [None] * len(starts)
    errors: list = [None] * len(starts)

    def work(i):
        err = None
        oracle.bind(i)
        try:
            out[i] = solve(starts[i], run=i, **kwargs)
        except BaseException as exc:
            err = errors[i] = exc
        finally:
            oracle.leave(err)

    threads = [threading.Thread(target=work, args=(i,), name=f"start-{i}") for i in range(len(starts))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    first = next((e for e in errors if e is not None and not isinstance(e, PopulationStopped)), None)
    if first is None:
        first = next((e for e in errors if e is not None), None)
    if first is not None:
        raise first
    return out
