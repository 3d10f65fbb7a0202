"""HDF5 fit log: every accepted iteration written and flushed, so a killed fit resumes without loss.

Layout (one file; a multi-start fit keeps one group per start)::

    /                      attrs: format = "jaxfoam-fitlog", version
    /multistart            attrs: seed; datasets: starts (S, p) initial guesses, unit (S, p) LHS design
    /runs/<run>            attrs: meta (JSON: kind, optimizer config, driver settings), rows (committed
                           iterations), seed, reason / evaluations / nonfinite / wall_time once finished
        x0                 (p,) starting point
        iteration          (K,)  accepted iteration number (row k is iteration k; row 0 is the start)
        x                  (K, p) parameters after the iteration, optimizer coordinates
        loss               (K,)  loss after the iteration, objective units
        evaluations        (K,)  cumulative objective evaluations
        nonfinite          (K,)  cumulative non-finite evaluations
        time               (K,)  wall time since the fit started, s (continues across resumes)
        state/<field>      (K, ...) optimizer-state leaves with at most ROW_LEAF_MAX elements, every row
        checksum           (K,)  uint64 digest of the row's stored values (version 2 on), checked on resume
        slots/<0|1>/<field>  larger leaves (an LM Jacobian of image residuals), written for iteration k
                           into slot k % 2 (attr iteration = k), so the slot of the last committed row is
                           never the one being overwritten when a kill interrupts a write; attr
                           checksum = the digest of its leaves

A row is committed by incrementing the `rows` attribute after all of its datasets are written, then the
file is flushed. Resuming restores the last committed row exactly (float64 values round-trip bit for
bit), so the continued fit is bit-identical to one that was never interrupted: the optimizers are
deterministic and hold all their memory in the state. The only random input of a fit, the multi-start
Latin-hypercube seed, is stored with the starts it produced. A log that is damaged (not HDF5, truncated,
rows missing, a checksum that does not match, non-finite parameters) is refused with a FitLogError.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import threading

import h5py
import numpy as np

FORMAT = "jaxfoam-fitlog"
VERSION = 2  # 2: per-row checksums
# Optimizer-state leaves up to this many elements are kept for every iteration; larger ones (an LM
# residual vector or Jacobian over image pixels) only for the last two iterations.
ROW_LEAF_MAX = 4096


class FitLogError(ValueError):
    """The fit log cannot be used as asked (wrong format, a different fit, inconsistent rows)."""


def _digest(arrays) -> np.uint64:
    """A 64-bit digest of (name, array) pairs: dtype, shape and bytes."""
    h = hashlib.blake2b(digest_size=8)
    for name, a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return np.frombuffer(h.digest(), np.uint64)[0]


DAMAGED = "start afresh without --resume, or use another log"


class FitLog:
    """An open fit-log file (`h5py`), usable as a context manager.

    Args:
      path: file path; created when missing (mode "a").
      mode: "a" (read/write) or "r" (read only).
    """

    def __init__(self, path, mode: str = "a"):
        if mode not in ("a", "r"):
            raise ValueError(f"FitLog mode must be 'a' or 'r', got {mode!r}")
        self.path = os.fspath(path)
        # The starts of a population (`fitting.optim.population`) write their runs from their own threads.
        self.lock = threading.RLock()
        if os.path.isdir(self.path):
            raise FitLogError(f"{self.path}: the fit log path is a directory")
        try:
            self.file = h5py.File(self.path, mode)
        except OSError as exc:
            raise FitLogError(f"{self.path}: cannot be read as a fit log (not HDF5, truncated or damaged: {exc}); "
                              f"{DAMAGED}") from exc
        attrs = self.file.attrs
        if "format" not in attrs and mode == "r":
            self.file.close()
            raise FitLogError(f"{self.path}: not a fit log (no format attribute)")
        if "format" not in attrs:
            attrs["format"] = FORMAT
            attrs["version"] = VERSION
        elif attrs["format"] != FORMAT:
            found = attrs["format"]
            self.file.close()
            raise FitLogError(f"{self.path}: attribute format={found!r}, expected {FORMAT!r}")

    def close(self):
        if self.file.id.valid:
            self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def flush(self):
        self.file.flush()

    def run(self, index: int) -> "RunLog":
        return RunLog(self, int(index))

    def runs(self) -> list[int]:
        """Indices of the runs present (committed rows or not)."""
        return sorted(int(k) for k in self.file.get("runs", {}).keys())

    def clear(self):
        """Delete every run and the multi-start record (a fresh fit into an existing file)."""
        for name in ("runs", "multistart"):
            if name in self.file:
                del self.file[name]
        self.file.flush()

    def write_starts(self, starts, unit, seed):
        """Record the multi-start initial guesses (S, p), their unit-cube design (S, p) and the seed."""
        if "multistart" in self.file:
            del self.file["multistart"]
        g = self.file.create_group("multistart")
        g.attrs["seed"] = -1 if seed is None else int(seed)
        g.create_dataset("starts", data=np.asarray(starts))
        g.create_dataset("unit", data=np.asarray(unit))
        self.file.flush()

    def read_starts(self):
        """(starts, unit, seed) as recorded, or None when no multi-start was logged."""
        if "multistart" not in self.file:
            return None
        g = self.file["multistart"]
        seed = int(g.attrs["seed"])
        return np.asarray(g["starts"]), np.asarray(g["unit"]), (None if seed < 0 else seed)


def _locked(method):
    """A RunLog method run under its log's lock."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self.log.lock:
            return method(self, *args, **kwargs)
    return run


class RunLog:
    """One run (one optimizer start) inside a `FitLog`."""

    def __init__(self, log: FitLog, index: int):
        self.log = log
        self.index = index
        self.name = f"runs/{index:04d}"

    @property
    def group(self):
        return self.log.file[self.name]

    @property
    def rows(self) -> int:
        """Committed rows (iterations + 1), 0 when the run has none."""
        if self.name not in self.log.file:
            return 0
        return int(self.group.attrs.get("rows", 0))

    @property
    def meta(self) -> dict:
        return json.loads(self.group.attrs["meta"])

    @_locked
    def begin(self, meta: dict, x0, seed=None):
        """Start the run afresh (deleting an earlier run with this index)."""
        f = self.log.file
        if self.name in f:
            del f[self.name]
        g = f.create_group(self.name)
        g.attrs["meta"] = json.dumps(meta, sort_keys=True)
        g.attrs["rows"] = 0
        g.attrs["seed"] = -1 if seed is None else int(seed)
        g.create_dataset("x0", data=np.asarray(x0))
        f.flush()

    @_locked
    def check(self, meta: dict, x0):
        """Raise FitLogError unless this run was started with the same settings and starting point."""
        logged = self.meta
        for key in sorted(set(meta) | set(logged)):
            if key in ("max_iterations", "max_evaluations"):
                continue  # a resumed fit may be given a larger budget
            if logged.get(key) != json.loads(json.dumps(meta.get(key))):
                raise FitLogError(f"{self.log.path} run {self.index}: cannot resume, {key}={logged.get(key)!r} "
                                  f"in the log but {meta.get(key)!r} now")
        if not np.array_equal(np.asarray(self.group["x0"]), np.asarray(x0)):
            raise FitLogError(f"{self.log.path} run {self.index}: cannot resume, the starting point x0 differs "
                              f"from the logged one {np.asarray(self.group['x0']).tolist()}")

    @_locked
    def append(self, *, iteration, x, loss, evaluations, nonfinite, time, state: dict):
        """Write one row (and the large state leaves into slot iteration % 2), commit it, flush."""
        g = self.group
        k = int(g.attrs["rows"])
        if iteration != k:
            raise FitLogError(f"{self.log.path} run {self.index}: row {k} expected, got iteration {iteration}")
        row = {"iteration": np.asarray(iteration, np.int64), "x": np.asarray(x), "loss": np.asarray(loss),
               "evaluations": np.asarray(evaluations, np.int64), "nonfinite": np.asarray(nonfinite, np.int64),
               "time": np.asarray(time, np.float64)}
        big = {}
        for name, value in state.items():
            value = np.asarray(value)
            if value.size <= ROW_LEAF_MAX:
                row[f"state/{name}"] = value
            else:
                big[name] = value
        if big:
            slot = g.require_group(f"slots/{k % 2}")
            for name, value in big.items():
                if name in slot and slot[name].shape == value.shape and slot[name].dtype == value.dtype:
                    slot[name][...] = value
                else:
                    if name in slot:
                        del slot[name]
                    slot.create_dataset(name, data=value)
            slot.attrs["iteration"] = k
        for name, value in row.items():
            if name not in g:
                g.create_dataset(name, shape=(0,) + value.shape, maxshape=(None,) + value.shape,
                                 dtype=value.dtype, chunks=True)
            ds = g[name]
            if ds.shape[0] < k + 1:
                ds.resize(k + 1, axis=0)
            ds[k] = value
        if big:
            slot.attrs["checksum"] = _digest(sorted((n, slot[n][()]) for n in big))
        # The digest of the values as stored (read back), so a resume recomputes it bit for bit.
        digest = _digest(sorted((name, g[name][k]) for name in row))
        if "checksum" not in g:
            g.create_dataset("checksum", shape=(0,), maxshape=(None,), dtype=np.uint64, chunks=True)
        if g["checksum"].shape[0] < k + 1:
            g["checksum"].resize(k + 1, axis=0)
        g["checksum"][k] = digest
        g.attrs["rows"] = k + 1
        self.log.file.flush()

    @_locked
    def restore(self) -> dict:
        """The committed rows: dict with history arrays and `state` (field -> array of the last row)."""
        try:
            return self._restore()
        except FitLogError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as exc:  # h5py's errors for a damaged file
            raise FitLogError(f"{self.log.path} run {self.index}: the log is damaged ({type(exc).__name__}: "
                              f"{exc}); {DAMAGED}") from exc

    def _restore(self) -> dict:
        k = self.rows
        where = f"{self.log.path} run {self.index}"
        if k == 0:
            raise FitLogError(f"{where}: no committed iteration to resume from")
        g = self.group
        row_names = ["iteration", "x", "loss", "evaluations", "nonfinite", "time"]
        row_names += [f"state/{name}" for name in g.get("state", {})]
        for name in row_names + (["checksum"] if "checksum" in g else []):
            if name not in g or g[name].shape[0] < k:
                held = g[name].shape[0] if name in g else 0
                raise FitLogError(f"{where}: the log claims {k} committed rows but '{name}' holds {held}; "
                                  f"the log is damaged; {DAMAGED}")
        if "checksum" in g:
            sums = np.asarray(g["checksum"][:k])
            old = int(self.log.file.attrs.get("version", 1)) < 2
            for i in range(k):
                if old and sums[i] == 0:  # a row a version-1 writer committed, before checksums
                    continue
                if _digest(sorted((name, g[name][i]) for name in row_names)) != sums[i]:
                    raise FitLogError(f"{where}: row {i} does not match its checksum (the log was altered or "
                                      f"damaged); {DAMAGED}")
        elif int(self.log.file.attrs.get("version", 1)) >= 2:
            raise FitLogError(f"{where}: the rows' checksums are missing; {DAMAGED}")
        out = {name: np.asarray(g[name][:k]) for name in row_names[:6]}
        if not np.all(np.isfinite(out["x"])):
            i = int(np.argmax(~np.all(np.isfinite(out["x"].reshape(k, -1)), axis=1)))
            raise FitLogError(f"{where}: row {i} holds non-finite parameters {out['x'][i].tolist()}; {DAMAGED}")
        state = {name: np.asarray(ds[k - 1]) for name, ds in g.get("state", {}).items()}
        slot_name = f"slots/{(k - 1) % 2}"
        if slot_name in g:
            slot = g[slot_name]
            if int(slot.attrs["iteration"]) != k - 1:
                raise FitLogError(f"{where}: slot {slot_name} holds iteration "
                                  f"{int(slot.attrs['iteration'])}, expected {k - 1}")
            leaves = {name: np.asarray(ds) for name, ds in slot.items()}
            if "checksum" in slot.attrs and _digest(sorted(leaves.items())) != slot.attrs["checksum"]:
                raise FitLogError(f"{where}: slot {slot_name} does not match its checksum (the log was altered "
                                  f"or damaged); {DAMAGED}")
            state.update(leaves)
        out["state"] = state
        out["finished"] = self.finished()
        return out

    @_locked
    def finish(self, reason: str, *, evaluations: int, nonfinite: int, wall_time: float, status: int):
        """Mark the run finished with its reason, final counters and the optimizer's final status code."""
        a = self.group.attrs
        a["reason"] = str(reason)
        a["final_status"] = int(status)
        a["final_evaluations"] = int(evaluations)
        a["final_nonfinite"] = int(nonfinite)
        a["wall_time"] = float(wall_time)
        self.log.file.flush()

    @_locked
    def unfinish(self):
        for key in ("reason", "final_status", "final_evaluations", "final_nonfinite", "wall_time"):
            if key in self.group.attrs:
                del self.group.attrs[key]

    def finished(self) -> dict | None:
        """{reason, status, evaluations, nonfinite, wall_time} when the run finished, else None."""
        a = self.group.attrs
        if "reason" not in a:
            return None
        return {"reason": str(a["reason"]), "status": int(a["final_status"]),
                "evaluations": int(a["final_evaluations"]),
                "nonfinite": int(a["final_nonfinite"]), "wall_time": float(a["wall_time"])}


def read_fitlog(path) -> dict:
    """Everything in a fit log as plain numpy: {"runs": {index: {...history, "meta", "finished"}},
    "multistart": (starts, unit, seed) or None}."""
    with FitLog(path, mode="r") as log:
        runs = {}
        for i in log.runs():
            run = log.run(i)
            if run.rows == 0:
                continue
            data = run.restore()
            data["meta"] = run.meta
            runs[i] = data
        return {"runs": runs, "multistart": log.read_starts()}
