"""Showcase scenes of the paper (Yue et al. 2015, section 6): load, simulate, render.

A showcase file (JSON) holds:
  name, description: text.
  scene: a scene description for `jaxfoam.load_scene` (kind, dim, domain, plates, initial shape, ...).
  params: mu, kappa, sigma_y, eta, m, rho (SI units; see docs/materials.md).
  colliders: a list of SDF colliders (`jaxfoam.sdf.collider_from_spec`): shapes the scene JSON cannot
    express (a face, crackers with holes, a pie tin), with a prescribed translation in time.
  resample: ResampleConfig fields, or null.  fracture: FractureConfig fields, or null.
  cpu, gpu: run settings {dx (m), ppc, duration (s), frames, dtype}: `cpu` is what runs here on a
    shared 2-core machine (short, coarse); `gpu` is the setting to scale up to on a GPU.
  views: pairs of axes to draw, e.g. [[0, 1], [0, 2]] (front and top views).
  camera: [azimuth, elevation] degrees of the surface renders (optional).
  measure: a list of measurements (experiments/showcase/measure.py), e.g. {"type": "detachment"}.

Usage: python experiments/showcase/showcase.py experiments/showcase/pie_throw.json [--gpu] [--reuse [--measure-only]]
Writes to experiments/showcase/out/<name>/: the particle view (frame_###.png, <name>.mp4,
<name>_sheet.png), the shaded surfaces (surface/frame_###.png, <name>_surface.mp4,
<name>_surface_sheet.png), the measurements (<name>_measure.json) and <name>.md; the frames themselves
go to frames.npz there (not committed), which --reuse renders and measures again without simulating
(--measure-only: measures only).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
jax.config.update("jax_enable_x64", True)  # float64 cases and fits; jaxfoam leaves the config alone
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import jaxfoam  # noqa: E402
from jaxfoam.fracture import FractureConfig  # noqa: E402
from jaxfoam.resample import ResampleConfig  # noqa: E402
from jaxfoam.sdf import collider_from_spec  # noqa: E402
from jaxfoam._trajectory import as_saved_trajectory  # noqa: E402
from jaxfoam.render import render_surface_sheet, render_surface_video  # noqa: E402

from measure import measure_all  # noqa: E402  (experiments/showcase/measure.py, beside this file)

HERE = Path(__file__).resolve().parent
KEYS = {"name", "description", "scene", "params", "colliders", "resample", "fracture", "cpu", "gpu", "views",
        "camera", "measure"}
RUN_KEYS = {"dx", "ppc", "duration", "frames", "dtype", "note"}
# Plastic rates drawn over this many decades below the top of the colour scale (creep to splash).
GAMMA_DECADES = 3.0
# Contact sheets are drawn at 70% of the frames' pixel size: small enough to commit (~150 kB).
SHEET_DPI = 70
# PNGs are stored with a palette of this many colours (about half the RGBA file size; the frames
# hold a three-decade colour map, grey and white).
PNG_COLORS = 64
# libx264 quality of the videos (imageio scale 0-10): 5 is ~2/3 the size of 6 on these frames.
VIDEO_QUALITY = 5


def load_showcase(path):
    """Parse a showcase file: returns a dict with scene, params, colliders, resample, fracture, cpu,
    gpu, views, name, description. Raises ValueError naming the field."""
    spec = json.loads(Path(path).read_text())
    unknown = sorted(set(spec) - KEYS)
    if unknown:
        raise ValueError(f"showcase {path}: unknown key(s) {unknown}; allowed {sorted(KEYS)}")
    for k in ("name", "scene", "params", "cpu"):
        if k not in spec:
            raise ValueError(f"showcase {path}: field '{k}' is required")
    scene = jaxfoam.load_scene(spec["scene"])
    params = jaxfoam.Params(**{k: float(v) for k, v in spec["params"].items()}).validate()
    if abs(float(params.kappa) - scene.kappa) > 1e-9 * scene.kappa or abs(float(params.rho) - scene.density) > 1e-9:
        raise ValueError(f"showcase {path}: params.kappa/rho must equal the scene's kappa/density")
    colliders = tuple(collider_from_spec(c, f"colliders[{i}]") for i, c in enumerate(spec.get("colliders", [])))
    resample = ResampleConfig(**spec["resample"]).validate(scene.dim) if spec.get("resample") is not None else None
    fracture = FractureConfig(**spec["fracture"]).validate(scene.dim) if spec.get("fracture") is not None else None
    for k in ("cpu", "gpu"):
        if k in spec:
            bad = sorted(set(spec[k]) - RUN_KEYS)
            if bad:
                raise ValueError(f"showcase {path}: {k}: unknown key(s) {bad}; allowed {sorted(RUN_KEYS)}")
    return dict(name=spec["name"], description=spec.get("description", ""), scene=scene, params=params,
                colliders=colliders, resample=resample, fracture=fracture, cpu=spec["cpu"], gpu=spec.get("gpu"),
                views=spec.get("views", [[0, 1]]), camera=spec.get("camera"), measure=spec.get("measure", []),
                spec=spec)


def make_simulator(show, settings, frame_times=None):
    """The Simulator of a showcase at the given settings (dict with dx, ppc, duration, frames, dtype)."""
    dtype = {"float32": jnp.float32, "float64": jnp.float64}[settings.get("dtype", "float32")]
    if frame_times is None:
        n = int(settings["frames"])
        frame_times = np.linspace(settings["duration"] / n, settings["duration"], n)
    return jaxfoam.Simulator(show["scene"], frame_times, show["params"], float(settings["dx"]),
                             ppc=settings.get("ppc"), dtype=dtype, resample=show["resample"],
                             fracture=show["fracture"], colliders=show["colliders"])


def observe(state, params):
    return dict(x=state.x, gamma_dot=state.gamma_dot, active=state.active, mass=state.mass)


# ----------------------------------------------------------------------------------------------
# Rendering (matplotlib): particles projected on two axes, nearer ones drawn on top, coloured by
# the plastic rate; colliders, plates and floor drawn as grey silhouettes.
# ----------------------------------------------------------------------------------------------

def _collider_silhouette(show, t, axes, lims, res=120):
    """Boolean image (res, res) of where any collider or plate covers the view at time t."""
    d = show["scene"].dim
    (a, b) = axes
    ga = np.linspace(*lims[0], res)
    gb = np.linspace(*lims[1], res)
    other = [k for k in range(d) if k not in axes]
    lo, hi = np.asarray(show["scene"].domain_min), np.asarray(show["scene"].domain_max)
    depth = [np.linspace(lo[k], hi[k], 24) for k in other]
    mesh = np.meshgrid(ga, gb, *depth, indexing="ij")
    pts = np.zeros(mesh[0].shape + (d,))
    pts[..., a] = mesh[0]
    pts[..., b] = mesh[1]
    for i, k in enumerate(other):
        pts[..., k] = mesh[2 + i]
    flat = jnp.asarray(pts.reshape(-1, d))
    hit = np.zeros(flat.shape[0], bool)
    for c in show["colliders"]:
        hit |= np.asarray(c.phi(flat, jnp.asarray(t, flat.dtype)) < 0)
    for p in show["scene"].plates:
        c = np.asarray(p.position(jnp.asarray(t)))
        hit |= np.all(np.abs(np.asarray(flat) - c[None, :]) <= np.asarray(p.half_size)[None, :], axis=1)
    hit = hit.reshape(pts.shape[:-1])
    while hit.ndim > 2:
        hit = hit.any(axis=-1)
    return hit.T  # rows along b


def render_frame(show, frame, t, path, lims, gmax):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    views = show["views"]
    fig, axs = plt.subplots(1, len(views), figsize=(4.2 * len(views), 4.2), squeeze=False)
    act = frame["active"]
    x = frame["x"][act]
    g = frame["gamma_dot"][act]
    logg = np.log10(np.maximum(g, gmax * 10 ** -GAMMA_DECADES))
    d = x.shape[1]
    for ax, (a, b), lim in zip(axs[0], views, lims):
        sil = _collider_silhouette(show, t, (a, b), lim)
        ax.imshow(sil, origin="lower", extent=(*lim[0], *lim[1]), cmap="Greys", vmin=0, vmax=2.5,
                  interpolation="nearest")
        other = [k for k in range(d) if k not in (a, b)]
        order = np.argsort(x[:, other[0]]) if other else np.arange(len(x))
        ax.scatter(x[order, a], x[order, b], c=logg[order], s=3, lw=0, cmap="viridis",
                   vmin=math.log10(gmax) - GAMMA_DECADES, vmax=math.log10(gmax))
        if sil.any() and not sil.all():
            # The colliders' outline over the points: material in front of a collider hides its
            # silhouette, the outline still shows where it is (e.g. foam above a cracker).
            ax.contour(np.linspace(*lim[0], sil.shape[1]), np.linspace(*lim[1], sil.shape[0]), sil.astype(float),
                       levels=[0.5], colors="0.3", linewidths=0.7)
        if show["scene"].floor_y is not None and b == 1:
            ax.axhline(show["scene"].floor_y, color="#8c8c8c", lw=2)
        ax.set_xlim(*lim[0])
        ax.set_ylim(*lim[1])
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
    fig.suptitle(f"{show['name']}  t = {t:.3f} s  (colour: log10 plastic rate, 1/s)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)
    _compact_png(path)


def _compact_png(path):
    """Rewrite a PNG with a PNG_COLORS palette (Pillow; left as is without it)."""
    try:
        from PIL import Image
    except ImportError:
        return
    with Image.open(path) as im:
        pal = im.convert("RGB").quantize(colors=PNG_COLORS)
    pal.save(path, optimize=True)


def run(path, gpu=False, out=None, reuse=False, measure_only=False):
    show = load_showcase(path)
    settings = show["gpu"] if gpu else show["cpu"]
    sim = make_simulator(show, settings)
    out = Path(out) if out else HERE / "out" / (show["name"] + ("_gpu" if gpu else ""))
    out.mkdir(parents=True, exist_ok=True)
    n0 = int(np.sum(np.asarray(sim.state0.active)))
    print(f"{show['name']}: {n0} points ({sim.state0.capacity} slots), {sim.total_substeps} substeps of "
          f"{sim.dt:.3g} s, grid {sim.grid.shape}", flush=True)
    saved = out / "frames.npz"
    if reuse:
        with np.load(saved) as z:
            frames, seconds = {k: z[k] for k in z.files if k != "seconds"}, float(z["seconds"])
    else:
        t0 = time.perf_counter()
        final, frames, health = sim.rollout(show["params"], observe=observe)
        frames = jax.device_get(frames)
        seconds = time.perf_counter() - t0
        sim.check(frames, health)
        frames = {k: np.asarray(v) for k, v in frames.items()}
        tmp = out / "frames.tmp.npz"
        np.savez(tmp, seconds=seconds, **frames)
        tmp.replace(saved)
    times = np.asarray(sim.plan.frame_times)
    measured = measure_all(show.get("measure", []), frames, times, show["scene"], show["colliders"],
                           float(settings["dx"]))
    (out / f"{show['name']}_measure.json").write_text(json.dumps(measured, indent=1) + "\n")
    if measure_only:
        print(f"{show['name']}: wrote {out / (show['name'] + '_measure.json')}", flush=True)
        return dict(seconds=seconds, frames=frames, sim=sim, measured=measured)
    lo, hi = np.asarray(show["scene"].domain_min), np.asarray(show["scene"].domain_max)
    lims = [((lo[a], hi[a]), (lo[b], hi[b])) for a, b in show["views"]]
    gmax = max(float(np.percentile(frames["gamma_dot"][frames["active"]], 99.5)), 1e-3)
    files = []
    for k, t in enumerate(times):
        f = out / f"frame_{k:03d}.png"
        render_frame(show, {key: v[k] for key, v in frames.items()}, float(t), f, lims, gmax)
        files.append(f)
    _sheet(files, out / f"{show['name']}_sheet.png")
    _video(files, out / f"{show['name']}.mp4")
    t1 = time.perf_counter()
    traj = as_saved_trajectory(dict(frames=frames, times=times, params=show["params"], scene=dict(show["spec"]["scene"], name=show["name"]),
                                            dx=float(settings["dx"]), dt=float(sim.dt), substeps=int(sim.substeps),
                                            ppc=settings.get("ppc")))
    camera = tuple(show["camera"]) if show.get("camera") else None
    render_surface_sheet(traj, out / f"{show['name']}_surface_sheet.png", camera=camera, colliders=show["colliders"])
    render_surface_video(traj, out / f"{show['name']}_surface.mp4", fps=10, camera=camera,
                         colliders=show["colliders"], frames_dir=out / "surface")
    render_s = time.perf_counter() - t1
    n_end = int(np.sum(frames["active"][-1]))
    text = (f"# {show['name']}\n\n{show['description']}\n\nSettings ({'gpu' if gpu else 'cpu'}): "
            f"{json.dumps(settings)}; {n0} points at start, {n_end} at the end; {sim.total_substeps} substeps "
            f"of {sim.dt:.3g} s; grid {sim.grid.shape}; rollout wall time {seconds:.1f} s (compile included) on "
            f"{'a GPU' if gpu else 'a shared 2-core CPU'}; surface renders {render_s:.0f} s.\n\n"
            f"Measurements: `{show['name']}_measure.json`.\n\n"
            f"![surfaces]({show['name']}_surface_sheet.png)\n\n![particles]({show['name']}_sheet.png)\n")
    (out / f"{show['name']}.md").write_text(text)
    print(f"{show['name']}: {seconds:.1f} s; wrote {out}", flush=True)
    return dict(seconds=seconds, frames=frames, sim=sim)


def _sheet(files, path, ncols=4, n=8):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pick = [files[i] for i in np.unique(np.linspace(0, len(files) - 1, min(n, len(files))).round().astype(int))]
    imgs = [plt.imread(f) for f in pick]
    nrows = int(math.ceil(len(imgs) / ncols))
    h, w = imgs[0].shape[:2]
    fig, axs = plt.subplots(nrows, ncols, figsize=(ncols * w / 100, nrows * h / 100), squeeze=False)
    for ax in axs.ravel():
        ax.axis("off")
    for ax, im in zip(axs.ravel(), imgs):
        ax.imshow(im)
    fig.subplots_adjust(0, 0, 1, 1, 0.01, 0.01)
    fig.savefig(path, dpi=SHEET_DPI)
    plt.close(fig)
    _compact_png(path)


def _video(files, path, fps=10):
    try:
        import imageio.v2 as imageio
    except ImportError:
        print("imageio not installed: no video (pip install 'jaxfoam[viz]')")
        return
    frames = [imageio.imread(f) for f in files]
    h = min(f.shape[0] for f in frames) // 16 * 16
    w = min(f.shape[1] for f in frames) // 16 * 16
    with imageio.get_writer(path, fps=fps, codec="libx264", quality=VIDEO_QUALITY, macro_block_size=16) as wr:
        for f in frames:
            wr.append_data(f[:h, :w, :3])


def main(argv=None):
    ap = argparse.ArgumentParser(description="Run and render a showcase scene.")
    ap.add_argument("scene", help="showcase JSON file")
    ap.add_argument("--gpu", action="store_true", help="use the file's 'gpu' settings (scale-up)")
    ap.add_argument("--out", help="output folder (default experiments/showcase/out/<name>)")
    ap.add_argument("--reuse", action="store_true", help="render and measure the frames.npz of an earlier run")
    ap.add_argument("--measure-only", action="store_true", help="with --reuse: only the measurements, no renders")
    args = ap.parse_args(argv)
    if args.measure_only and not args.reuse:
        ap.error("--measure-only needs --reuse (the frames of an earlier run)")
    run(args.scene, args.gpu, args.out, args.reuse, args.measure_only)


if __name__ == "__main__":
    main()
