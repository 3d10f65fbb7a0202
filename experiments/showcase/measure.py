"""Measurements of the showcase scenes: what the paper's pictures show, as numbers.

Each takes the rollout's frames (x (T, N, d) m, mass (T, N) kg, active (T, N)) and frame times (T,) s.
Heights are binned in horizontal slabs of `h` m (the grid's dx): a slab holding fewer than `min_count`
points is empty, so loose debris points neither close a gap nor make a peak.
  detachment: the first frame whose foam below a plate has an empty slab between occupied ones (the
    cap left on the plate and the falling body), and the frame before it.
  wobble: the landed body's centre-of-mass height (points below that gap) after it reaches the floor:
    its peak-to-peak amplitude in consecutive windows and the decay time of a log-linear fit to them.
  fraction_near: the mass fraction within `distance` m of a collider (phi < distance) at given times.
  column_height: the height above base_y of the column of slabs occupied without a gap from base_y up,
    over a footprint (x and z ranges, m), at given times.
  mass_in_box: the mass fraction inside a box (x, y, z ranges, m) at given times.
  pieces: the pieces of foam at given times: the cells of size h holding a point, joined across faces,
    edges and corners (skimage.measure.label); pieces of at least min_fraction of the mass are counted.
"""
from __future__ import annotations

import math

import numpy as np

MEASURES = ("detachment", "wobble", "fraction_near", "column_height", "mass_in_box", "pieces")


def occupied_slabs(y: np.ndarray, lo: float, hi: float, h: float, min_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Slab bottoms (n,) m from lo up to hi and whether each holds at least min_count of the heights y."""
    n = max(int(math.ceil((hi - lo) / h)), 1)
    counts = np.bincount(np.clip(((y - lo) / h).astype(int), 0, n - 1), minlength=n) if len(y) else np.zeros(n, int)
    return lo + h * np.arange(n), counts >= min_count


def gap_height(y: np.ndarray, top: float, h: float, min_count: int) -> float | None:
    """The bottom of the highest empty slab with occupied slabs above and below it, among heights y below
    `top` (m); None when the occupied slabs are contiguous."""
    y = y[y < top]
    if len(y) == 0:
        return None
    bottoms, occ = occupied_slabs(y, float(y.min()), top, h, min_count)
    idx = np.nonzero(occ)[0]
    if len(idx) < 2:
        return None
    inner = np.nonzero(~occ[idx[0]:idx[-1] + 1])[0]
    return float(bottoms[idx[0] + inner[-1]]) if len(inner) else None


def detachment(frames, times, top: float, h: float, min_count: int) -> dict:
    """First frame with a gap below `top` (the plate's lower face, m): its time, the previous frame's, and
    the gap height of every frame (None where there is none)."""
    gaps = []
    for k in range(len(times)):
        a = frames["active"][k]
        gaps.append(gap_height(frames["x"][k][a, 1], top, h, min_count))
    first = next((k for k, g in enumerate(gaps) if g is not None), None)
    return dict(time=None if first is None else float(times[first]),
                after=None if first is None or first == 0 else float(times[first - 1]), gaps=gaps)


def wobble(frames, times, gaps, floor_y: float, h: float, window: float) -> dict:
    """The landed body's centre-of-mass height (m) from the first frame after detachment whose body reaches
    within one slab of the floor: peak-to-peak amplitude per window of `window` s, and the decay time (s)
    of a log-linear fit of amplitude on window centre (None with fewer than 2 windows or a zero amplitude)."""
    com, t_com = [], []
    for k, g in enumerate(gaps):
        if g is None:
            continue
        a = frames["active"][k]
        y, m = frames["x"][k][a, 1], frames["mass"][k][a]
        body = y < g
        if not body.any():
            continue
        if not t_com and y[body].min() > floor_y + h:
            continue  # still falling
        com.append(float(np.sum(y[body] * m[body]) / np.sum(m[body])))
        t_com.append(float(times[k]))
    if not com:
        return dict(landing=None, windows=[], amplitudes=[], decay_time=None, com=[], times=[])
    t_com, com = np.asarray(t_com), np.asarray(com)
    edges = np.arange(t_com[0], t_com[-1] + 1e-9, window)
    windows, amps = [], []
    for lo in edges:
        sel = (t_com >= lo) & (t_com < lo + window)
        if sel.sum() >= 3:
            windows.append(float(lo + 0.5 * window))
            amps.append(float(com[sel].max() - com[sel].min()))
    decay = None
    if len(amps) >= 2 and min(amps) > 0:
        slope = np.polyfit(windows, np.log(amps), 1)[0]
        decay = float(-1.0 / slope) if slope < 0 else math.inf
    return dict(landing=float(t_com[0]), windows=windows, amplitudes=amps, decay_time=decay,
                com=com.tolist(), times=t_com.tolist())


def fraction_near(frames, times, collider, distance: float, at) -> dict:
    """Mass fraction of the foam with the collider's phi < distance (m) at the frames nearest the times `at`."""
    import jax.numpy as jnp

    out = {}
    for t in at:
        k = int(np.argmin(np.abs(np.asarray(times) - t)))
        a = frames["active"][k]
        x, m = frames["x"][k][a], frames["mass"][k][a]
        phi = np.asarray(collider.phi(jnp.asarray(x), jnp.asarray(times[k], jnp.asarray(x).dtype)))
        out[f"{float(times[k]):.3f}"] = float(np.sum(m[phi < distance]) / np.sum(m))
    return out


def column_height(frames, times, base_y: float, footprint, h: float, min_count: int, at) -> dict:
    """Height (m) above base_y of the gap-free column of occupied slabs over the footprint ((x0, x1),
    (z0, z1)) m, at the frames nearest the times `at`."""
    (x0, x1), (z0, z1) = footprint
    out = {}
    for t in at:
        k = int(np.argmin(np.abs(np.asarray(times) - t)))
        x = frames["x"][k][frames["active"][k]]
        sel = (x[:, 0] >= x0) & (x[:, 0] <= x1) & (x[:, 2] >= z0) & (x[:, 2] <= z1) & (x[:, 1] > base_y)
        y = x[sel, 1]
        height = 0.0
        if len(y):
            bottoms, occ = occupied_slabs(y, base_y, float(y.max()) + h, h, min_count)
            run = np.argmin(occ) if not occ.all() else len(occ)
            height = float(bottoms[run - 1] + h - base_y) if run > 0 else 0.0
        out[f"{float(times[k]):.3f}"] = height
    return out


def _frame_at(times, t) -> int:
    return int(np.argmin(np.abs(np.asarray(times) - t)))


def mass_in_box(frames, times, box, at) -> dict:
    """Mass fraction of the foam inside box ((x0, x1), (y0, y1), (z0, z1)) m at the frames nearest `at`."""
    lo, hi = np.asarray(box, float).T
    out = {}
    for t in at:
        k = _frame_at(times, t)
        a = frames["active"][k]
        x, m = frames["x"][k][a], frames["mass"][k][a]
        inside = np.all((x >= lo) & (x <= hi), axis=1)
        out[f"{float(times[k]):.3f}"] = float(np.sum(m[inside]) / np.sum(m))
    return out


def pieces(frames, times, h: float, min_fraction: float, at) -> dict:
    """Pieces of the foam at the frames nearest `at`: {time: {"count": pieces holding at least
    min_fraction of the mass, "fractions": their mass fractions, largest first}}."""
    from skimage.measure import label

    out = {}
    for t in at:
        k = _frame_at(times, t)
        a = frames["active"][k]
        x, m = frames["x"][k][a], frames["mass"][k][a]
        cell = np.floor((x - x.min(0)) / h).astype(int)
        occupied = np.zeros(cell.max(0) + 1, bool)
        occupied[tuple(cell.T)] = True
        labels = label(occupied, connectivity=x.shape[1])[tuple(cell.T)]
        mass = np.bincount(labels, weights=m) / np.sum(m)
        big = np.sort(mass[mass >= min_fraction])[::-1]
        out[f"{float(times[k]):.3f}"] = dict(count=int(len(big)), fractions=[round(float(f), 4) for f in big])
    return out


def measure_all(spec: list, frames, times, scene, colliders, dx: float) -> dict:
    """Run the showcase file's `measure` list: each entry {"type": one of MEASURES, ...}; returns a dict
    keyed by type. Raises ValueError naming an unknown type or a missing field."""
    results, det = {}, None
    n = int(np.max(np.sum(frames["active"], axis=1)))
    for item in spec:
        kind = item.get("type")
        if kind not in MEASURES:
            raise ValueError(f"measure: type {kind!r} unknown; allowed {list(MEASURES)}")
        min_count = max(int(item.get("min_fraction", 0.002) * n), 2)
        if kind == "detachment":
            plate = scene.plates[int(item.get("plate", 0))]
            top = float(np.asarray(plate.position(float(times[0])))[1] - np.asarray(plate.half_size)[1])
            det = detachment(frames, times, top, dx, min_count)
            results[kind] = {k: v for k, v in det.items() if k != "gaps"}
        elif kind == "wobble":
            if det is None:
                raise ValueError("measure: 'wobble' needs a 'detachment' entry before it")
            results[kind] = wobble(frames, times, det["gaps"], float(scene.floor_y), dx, float(item["window"]))
        elif kind == "fraction_near":
            results[kind] = fraction_near(frames, times, colliders[int(item["collider"])],
                                          float(item.get("distance", dx)), item["at"])
        elif kind == "column_height":
            results[kind] = column_height(frames, times, float(item["base_y"]), item["footprint"], dx, min_count,
                                          item["at"])
        elif kind == "mass_in_box":
            results.setdefault(kind, {})[item.get("name", "box")] = mass_in_box(frames, times, item["box"], item["at"])
        else:
            results[kind] = pieces(frames, times, dx, float(item.get("min_fraction", 0.01)), item["at"])
    return results
