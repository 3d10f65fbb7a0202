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
        slots/<0|1>/<field>  larger leaves (an LM Jacobian of image residuals), written for iteration k
                           into slot k % 2 (attr iteration = k), so the slot of the last committed row is
                           never the one being overwritten when a kill interrupts a write

A row is committed by incrementing the `rows` attribute after all of its datasets are written, then the
file is flushed. Resuming restores the last committed row exactly (float64 values round-trip bit for
bit), so the continued fit is bit-identical to one that was never interrupted: the optimizers are
deterministic and hold all their memory in the state. The only random input of a fit, the multi-start
Latin-hypercube seed, is stored with the starts it produced.
"""
from __future__ import annotations

import json
import os

import h5py
import numpy as np

FORMAT = "jaxfoam-fitlog"
VERSION = 1
# Optimizer-state leaves up to this many elements are kept for every iteration; larger ones (an LM
# residual vector or Jacobian over image pixels) only for the last two iterations.
ROW_LEAF_MAX = 4096


class FitLogError(ValueError):
    """The fit log cannot be used as asked (wrong format, a different fit, inconsistent rows)."""


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
        self.file = h5py.File(self.path, mode)
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
        g.attrs["rows"] = k + 1
        self.log.file.flush()

    def restore(self) -> dict:
        """The committed rows: dict with history arrays and `state` (field -> array of the last row)."""
        k = self.rows
        if k == 0:
            raise FitLogError(f"{self.log.path} run {self.index}: no committed iteration to resume from")
        g = self.group
        out = {name: np.asarray(g[name][:k]) for name in ("iteration", "x", "loss", "evaluations",
                                                           "nonfinite", "time")}
        state = {name: np.asarray(ds[k - 1]) for name, ds in g.get("state", {}).items()}
        slot_name = f"slots/{(k - 1) % 2}"
        if slot_name in g:
            slot = g[slot_name]
            if int(slot.attrs["iteration"]) != k - 1:
                raise FitLogError(f"{self.log.path} run {self.index}: slot {slot_name} holds iteration "
                                  f"{int(slot.attrs['iteration'])}, expected {k - 1}")
            state.update({name: np.asarray(ds) for name, ds in slot.items()})
        out["state"] = state
        out["finished"] = self.finished()
        return out

    def finish(self, reason: str, *, evaluations: int, nonfinite: int, wall_time: float, status: int):
        """Mark the run finished with its reason, final counters and the optimizer's final status code."""
        a = self.group.attrs
        a["reason"] = str(reason)
        a["final_status"] = int(status)
        a["final_evaluations"] = int(evaluations)
        a["final_nonfinite"] = int(nonfinite)
        a["wall_time"] = float(wall_time)
        self.log.file.flush()

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
