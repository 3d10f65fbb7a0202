"""Export a trajectory's frames for renderers and plotting tools: particle clouds and surfaces.

Per exported frame k (files in one folder, written atomically; formats in docs/export.md):

- `particles_KKKK.ply`: the active particles as a binary PLY point cloud: x, y, z (m; z = 0 in 2D),
  the velocity vx, vy[, vz] (m/s), every other per-particle field of the file (gamma_dot 1/s, s Pa,
  J, ...; a vector field as name_0, name_1, ...) in the file's own dtype, so values read back exactly,
  and `id`, the particle's slot in the trajectory (follows a particle across frames).
- `surface_KKKK.EXT`: the surface of the material (jaxfoam._surface): in 3D a closed triangle mesh
  (`ply` with vertex normals, or `obj`); in 2D the outline as closed loops (`ply` vertices and edges,
  `obj` line loops, `svg` one filled path, or `csv` rows loop, x_m, y_m).
- `export.json`: the frames written, their times (s), files, particle counts and the enclosed volume
  (m^3) or area (m^2) of each surface.

Needs the `export` extra (scikit-image for surfaces, plyfile for PLY), imported only when used.
"""
from __future__ import annotations

import itertools
import json
import os

import numpy as np

from ._scene import DEFAULT_PPC
from ._trajectory import FRAME_UNITS, as_saved_trajectory
from .guards import EXPORT_HINT, atomic_output

FORMATS = ("ply", "obj", "svg", "csv")
# Surface formats by dimension: svg and csv hold polygons, not meshes.
SURFACE_FORMATS = {2: ("ply", "obj", "svg", "csv"), 3: ("ply", "obj")}
MANIFEST = "export.json"
# SVG drawings are in mm (1 user unit = 1 mm) with this margin around the outline, mm.
SVG_MARGIN_MM = 5.0
# Frame numbers in file names have this many digits (zero-padded, so names sort in time order).
FRAME_DIGITS = 4


def _require_plyfile():
    try:
        import plyfile
    except ImportError as exc:
        raise ImportError(f"PLY files need plyfile: {EXPORT_HINT}") from exc
    return plyfile


def parse_frames(spec, num_frames: int, option: str = "--frames") -> np.ndarray:
    """Frame indices from "all", an int, a sequence of ints, or text of comma-separated indices and
    Python-style ranges "start:stop[:step]" (negative indices count from the end).

    Raises ValueError naming the option, the bad value and the allowed range."""
    allowed = (f"this trajectory has {num_frames} frames: indices 0 to {num_frames - 1}, or -{num_frames} "
               f"to -1 counting from the end")
    if num_frames < 1:
        raise ValueError(f"{option}: the trajectory holds no frame to export")
    if spec is None or (isinstance(spec, str) and spec.strip().lower() == "all"):
        return np.arange(num_frames)
    items = spec.split(",") if isinstance(spec, str) else np.atleast_1d(spec).tolist()
    out = []
    for item in items:
        text = str(item).strip()
        parts = text.split(":")
        try:
            numbers = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            numbers = None
        if numbers is None or len(parts) > 3 or (len(parts) == 3 and numbers[2] == 0):
            raise ValueError(f"{option}: {text!r} is not a frame index or a range start:stop[:step] "
                             f"(e.g. 'all', '0,5,-1', '0:10:2'; {allowed})")
        if len(parts) == 1:
            if not -num_frames <= numbers[0] < num_frames:
                raise ValueError(f"{option}: frame {numbers[0]} is out of range ({allowed})")
            out.append(numbers[0] % num_frames)
            continue
        for end in numbers[:2]:
            if end is not None and not -num_frames <= end <= num_frames:
                raise ValueError(f"{option}: range {text!r} reaches frame {end}, out of range ({allowed})")
        picked = list(range(num_frames))[slice(*numbers)]
        if not picked:
            raise ValueError(f"{option}: range {text!r} selects no frame ({allowed})")
        out += picked
    return np.array(sorted(set(out)), int)


def check_format(fmt: str, dim: int, option: str = "--format") -> str:
    """The surface format, checked against the trajectory's dimension (ValueError naming the choices)."""
    fmt = str(fmt).lower().lstrip(".")
    if fmt not in FORMATS:
        raise ValueError(f"{option} must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt not in SURFACE_FORMATS[dim]:
        raise ValueError(f"{option} {fmt} holds polygons, not meshes: a {dim}D trajectory's surface is written as "
                         f"{' or '.join(SURFACE_FORMATS[dim])}")
    return fmt


def check_folder(path, option: str = "--out") -> str:
    """An output folder, created when missing; refuses a file and an unwritable folder."""
    out = os.fspath(path)
    if not out:
        raise ValueError(f"{option} must be a folder path, got an empty string")
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"{option} {out!r} is a file; give a folder for the exported files")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{option} {out!r}: cannot create the folder ({exc.strerror})") from exc
    if not os.access(out, os.W_OK):
        raise ValueError(f"{option} {out!r}: the folder is not writable")
    return out


def particle_attributes(traj, k: int) -> dict:
    """The active particles of frame k as named columns (n,): x, y, z (m), vx, vy[, vz] (m/s), the
    other per-particle fields in their stored dtype, and id (the slot index, uint32)."""
    a = np.asarray(traj.frames["active"][k], bool)
    x = np.asarray(traj.frames["x"][k])[a]
    cols = {axis: x[:, i] for i, axis in enumerate("xyz"[:x.shape[1]])}
    if x.shape[1] == 2:
        cols["z"] = np.zeros(len(x), x.dtype)  # renderers expect three coordinates
    for name in sorted(traj.frames, key=lambda n: (n != "v", n)):
        if name in ("x", "active"):
            continue
        values = np.asarray(traj.frames[name][k])[a]
        if values.dtype == bool:
            values = values.astype(np.uint8)
        if name == "v" and values.ndim == 2:
            cols.update({f"v{axis}": values[:, i] for i, axis in enumerate("xyz"[:values.shape[1]])})
        elif values.ndim == 1:
            cols[name] = values
        else:
            flat = values.reshape(len(values), -1)
            cols.update({f"{name}_{i}": flat[:, i] for i in range(flat.shape[1])})
    cols["id"] = np.nonzero(a)[0].astype(np.uint32)
    return cols


def write_particles_ply(path, cols: dict) -> str:
    """A binary little-endian PLY point cloud with one vertex property per column."""
    plyfile = _require_plyfile()
    n = len(next(iter(cols.values())))
    table = np.empty(n, dtype=[(name, c.dtype.newbyteorder("<")) for name, c in cols.items()])
    for name, c in cols.items():
        table[name] = c
    data = plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")], byte_order="<",
                           comments=["jaxfoam particles; units: x y z m, v m/s, gamma_dot 1/s, s Pa"])
    with atomic_output(path) as tmp:
        data.write(tmp)
    return os.fspath(path)


def write_mesh(path, verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, fmt: str) -> str:
    """A triangle mesh (vertices (v, 3) m, faces (f, 3) counter-clockwise outside, unit normals (v, 3))
    as binary PLY or as OBJ."""
    with atomic_output(path) as tmp:
        if fmt == "ply":
            plyfile = _require_plyfile()
            vt = np.empty(len(verts), dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
            for i, k in enumerate("xyz"):
                vt[k], vt["n" + k] = verts[:, i], normals[:, i]
            ft = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
            ft["vertex_indices"] = faces
            plyfile.PlyData([plyfile.PlyElement.describe(vt, "vertex"), plyfile.PlyElement.describe(ft, "face")],
                            byte_order="<", comments=["jaxfoam surface; units: m"]).write(tmp)
        else:
            with open(tmp, "w") as f:
                f.write("# jaxfoam surface (m), faces counter-clockwise seen from outside\n")
                np.savetxt(f, verts, fmt="v %.9g %.9g %.9g")
                np.savetxt(f, normals, fmt="vn %.6f %.6f %.6f")
                idx = np.repeat(faces + 1, 2, axis=1)
                np.savetxt(f, idx, fmt="f %d//%d %d//%d %d//%d")
    return os.fspath(path)


def write_outline(path, loops: list, fmt: str) -> str:
    """Closed 2D loops [(k, 2) m; outer ones counter-clockwise, holes clockwise] as PLY (vertices with
    z = 0 and edges), OBJ (one `l` line loop each, its first vertex repeated at the end), SVG (one path,
    even-odd fill, mm, y up on the page) or CSV (loop, x_m, y_m)."""
    with atomic_output(path) as tmp:
        pts = np.concatenate(loops) if loops else np.zeros((0, 2))
        starts = np.cumsum([0] + [len(p) for p in loops])
        if fmt == "ply":
            plyfile = _require_plyfile()
            vt = np.empty(len(pts), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
            vt["x"], vt["y"], vt["z"] = pts[:, 0], pts[:, 1], 0.0
            edges = [np.stack([np.arange(a, b), np.roll(np.arange(a, b), -1)], 1) for a, b in itertools.pairwise(starts)]
            e = np.concatenate(edges) if edges else np.zeros((0, 2), int)
            et = np.empty(len(e), dtype=[("vertex1", "<i4"), ("vertex2", "<i4")])
            et["vertex1"], et["vertex2"] = e[:, 0], e[:, 1]
            plyfile.PlyData([plyfile.PlyElement.describe(vt, "vertex"), plyfile.PlyElement.describe(et, "edge")],
                            byte_order="<", comments=["jaxfoam outline; units: m"]).write(tmp)
        elif fmt == "obj":
            with open(tmp, "w") as f:
                f.write("# jaxfoam outline (m): closed line loops, outer counter-clockwise, holes clockwise\n")
                np.savetxt(f, pts, fmt="v %.9g %.9g 0")
                f.writelines("l " + " ".join(str(i + 1) for i in [*range(a, b), a]) + "\n"
                             for a, b in itertools.pairwise(starts))
        elif fmt == "csv":
            with open(tmp, "w") as f:
                f.write("loop,x_m,y_m\n")
                for i, p in enumerate(loops):
                    np.savetxt(f, np.column_stack([np.full(len(p), i), p]), fmt=["%d", "%.9g", "%.9g"], delimiter=",")
        else:
            _write_svg(tmp, loops, pts)
    return os.fspath(path)


def _write_svg(tmp, loops, pts):
    mm = pts * 1e3
    lo = (mm.min(0) if len(mm) else np.zeros(2)) - SVG_MARGIN_MM
    hi = (mm.max(0) if len(mm) else np.zeros(2)) + SVG_MARGIN_MM
    w, h = hi - lo
    paths = " ".join("M " + " L ".join(f"{x - lo[0]:.4f},{hi[1] - y:.4f}" for x, y in p * 1e3) + " Z"
                     for p in loops)
    with open(tmp, "w") as f:
        f.write(f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.3f}mm" height="{h:.3f}mm" '
                f'viewBox="0 0 {w:.4f} {h:.4f}">\n'
                f'<!-- jaxfoam outline; 1 unit = 1 mm; x from {lo[0]:.4f} mm, y up from {lo[1]:.4f} mm -->\n'
                f'<path d="{paths}" fill="#e8e4da" stroke="#333333" stroke-width="0.3" fill-rule="evenodd"/>\n'
                '</svg>\n')


def export_trajectory(traj, out_dir, fmt: str = "ply", frames=None, particles: bool = True,
                      surface: bool = True) -> dict:
    """Write frames of a trajectory as particle clouds and surfaces (module docstring); returns the
    manifest written to `out_dir/export.json`.

    Args:
      traj: a trajectory file path, a SavedTrajectory or a `jaxfoam.Trajectory`.
      out_dir: folder for the files (created; files there of the same names are replaced).
      fmt: surface format, "ply" or "obj" (3D); "ply", "obj", "svg" or "csv" (2D).
      frames: "all" (default), indices, or text such as "0,5,-1" or "0:10:2" (`parse_frames`).
      particles, surface: which files to write.
    Every argument is checked before any file is written.
    """
    from . import _surface

    traj = as_saved_trajectory(traj)
    fmt = check_format(fmt, traj.dim, "fmt")
    indices = parse_frames(frames, traj.num_frames, "frames")
    out_dir = check_folder(out_dir, "out_dir")
    if surface:
        _surface.require_skimage()
    if particles or (surface and fmt == "ply"):
        _require_plyfile()
    act = np.asarray(traj.frames["active"], bool)
    entries = []
    for k in indices:
        entry = {"index": int(k), "time_s": float(traj.times[k]), "particles_count": int(act[k].sum())}
        stem = f"{k:0{FRAME_DIGITS}d}"
        if particles:
            entry["particles"] = f"particles_{stem}.ply"
            write_particles_ply(os.path.join(out_dir, entry["particles"]), particle_attributes(traj, k))
        if surface:
            entry["surface"] = f"surface_{stem}.{fmt}"
            path = os.path.join(out_dir, entry["surface"])
            result = _surface.frame_surface(traj, k)
            if traj.dim == 3:
                verts, faces, normals = result
                write_mesh(path, verts, faces, normals, fmt)
                entry.update(vertices=len(verts), triangles=len(faces),
                             enclosed_volume_m3=_surface.mesh_volume(verts, faces))
            else:
                write_outline(path, result, fmt)
                entry.update(loops=len(result), enclosed_area_m2=float(sum(_surface.signed_area(p) for p in result)))
        entries.append(entry)
    spacing = _surface.particle_spacing(traj.dx, traj.ppc or DEFAULT_PPC[traj.dim], traj.dim)
    manifest = {"format": "jaxfoam-export", "format_version": 1, "dim": traj.dim,
                "surface_format": fmt if surface else None,
                "units": {**FRAME_UNITS, "x y z": "m", "vx vy vz": "m/s", "id": "slot index"},
                "iso_level": _surface.ISO_LEVEL, "smoothing_length_m": _surface.SMOOTHING * spacing,
                "frames": entries}
    with atomic_output(os.path.join(out_dir, MANIFEST)) as tmp, open(tmp, "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest
