"""End to end from video (issue 34, item 5): does `jaxfoam track` on a camera's video of a reference run
give the silhouettes, and the fit, that the exact masks give?

Per case: the independent reference simulator (experiments/reference, no jaxfoam code) runs the case's
parameter set again (the run of its silhouette file) and keeps the particles at the video's own frame
times (a frame rate that is not a multiple of the data's); `experiments.reference.camera` draws each
frame as a camera records it (lit, shaded foam with a soft drop shadow, the plate, a textured
background, lens blur, sensor noise) and encodes H.264, plus a photo of the empty scene.
`jaxfoam track` turns the video into a silhouette file (the empty-scene photo as background, the video's
pixel size and origin, --downsample to the data's 2.5 mm pixels); the reference draws the exact masks
at the same frame times on the same pixel grid. Reported: IoU per frame (over pixels of weight > 0 in
both), then `jaxfoam fit` with every default on both files and whether each parameter of the tracked
fit lies in the exact fit's 95% interval (and in its interval at the optimum, `interval_local`).

Files: experiments/results/video_end_to_end/ (video, empty-scene photo, both silhouette files, both fit
results); the particle recordings and fit logs go to out/video_end_to_end/ (a rerun reuses them and
resumes a killed fit). --quick: a coarse reference run (dx x2), the first frames, no fits.

Usage: python -m experiments video_end_to_end [--quick]
Writes experiments/results/video_end_to_end[_quick].md and .png. SI units.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _common as C

NAME = "video_end_to_end"
ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "out" / NAME  # recordings (MBs) and fit logs (tens of MB): kept out of git
IOU_GOAL = 0.98  # issue 34 item 5: tracked against exact masks, every frame
# Tracker options beyond the empty-scene photo: white foam (its shadow is no foam), no closing (no cracks
# to bridge; it rounds off the air pocket under the landed drop), half-contrast edges (the shaded rim).
TRACK_OPTIONS = ["--polarity", "brighter", "--close", 0, "--edges", "half"]
# The same video tracked with fewer of those options (all take the empty-scene photo as background).
ABLATION = (("(defaults)", []), ("--polarity brighter", ["--polarity", "brighter"]),
            ("--polarity brighter --close 0", ["--polarity", "brighter", "--close", 0]))
OTHER_RIMS = (0.004,)  # m: a rounder foam edge, its rim darker over more of a pixel


@dataclasses.dataclass(frozen=True)
class VideoCase:
    """A reference case filmed: parameter set, frame rate (1/s), the video's pixel size (m), the tracker's
    downsampling to the data's pixels, and the camera's seed (texture and noise)."""

    case: str
    set_index: int
    fps: float
    pixel_size: float
    downsample: int
    seed: int

    @property
    def stem(self):
        return f"{self.case}_set{self.set_index}_{self.fps:g}fps"


# 25 fps against the data's 30 Hz (13 frames on 0.4 s); 0.625 mm pixels, 4 per 2.5 mm data pixel.
FULL = (VideoCase("drop_2d", 0, 25.0, 0.000625, 4, 0),)
QUICK = (VideoCase("drop_2d", 0, 25.0, 0.00125, 2, 0),)
QUICK_REFINE = 2.0     # reference dx = fit default / 2 in the quick run (8x fewer steps than 4x)
QUICK_DURATION = 0.12  # s: the first frames only


def recording(vc, duration, refine=None, progress=print):
    """The reference run's particles at the video's frame times, cached in out/ (npz)."""
    from experiments.reference import camera as K

    path = WORK / f"{vc.stem}{'' if refine is None else f'_refine{refine:g}'}_{duration:g}s.npz"
    times = K.video_times(duration, vc.fps)
    if path.exists():
        z = np.load(path)
        if np.array_equal(z["times"], times):
            return dict(times=z["times"], x=z["x"], spacing=float(z["spacing"]), dx=float(z["dx"]),
                        steps=int(z["steps"]), wall_s=float(z["wall_s"]), cached=True)
    rec = K.record(vc.case, vc.set_index, times, refine=refine, progress=progress)
    WORK.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".partial.npz")
    np.savez(tmp, times=rec["times"], x=rec["x"], spacing=rec["spacing"], dx=rec["dx"], steps=rec["steps"],
             wall_s=rec["wall_s"])
    os.replace(tmp, path)
    return dict(rec, cached=False)


def jaxfoam_cli(args, log=None):
    """Run `jaxfoam ARGS` in a subprocess (niced: the machine is shared); raises on a non-zero exit."""
    cmd = ["nice", "-n", "5", sys.executable, "-m", "jaxfoam"] + [str(a) for a in args]
    t0 = time.perf_counter()
    with open(log, "a") if log else open(os.devnull, "w") as out:
        rc = subprocess.call(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)
    if rc:
        raise RuntimeError(f"{' '.join(cmd)} failed with exit {rc} (log: {log})")
    return time.perf_counter() - t0


def iou_per_frame(tracked, exact):
    """IoU per frame of two silhouette files' masks over the pixels of weight > 0 in both."""
    out = []
    for t in range(tracked.masks.shape[0]):
        w = (np.asarray(tracked.weights[t]) > 0) & (np.asarray(exact.weights[t]) > 0)
        out.append(C.iou(np.asarray(tracked.masks[t], bool) & w, np.asarray(exact.masks[t], bool) & w))
    return np.array(out)


def film(vc, quick, folder, progress=print):
    """Record, render, encode, track and compare one case. Returns a dict of what was measured."""
    from experiments.reference import camera as K
    from experiments.reference.generate import CASES, PIXEL_SIZE, parameter_sets
    from experiments.reference.scene import SCENES_DIR, RefScene
    from experiments.reference.silhouettes import Camera, write
    from fitting import read_silhouettes

    case = CASES[vc.case]
    scene = RefScene(str(SCENES_DIR / f"{vc.case}.json"))
    rec = recording(vc, QUICK_DURATION if quick else case.duration, QUICK_REFINE if quick else None, progress)
    times = rec["times"]
    cam = K.video_camera(scene.lo, scene.hi, vc.pixel_size)
    data_cam = Camera(vc.pixel_size * vc.downsample, cam.origin,
                      (cam.shape[0] // vc.downsample, cam.shape[1] // vc.downsample))
    if abs(data_cam.pixel_size - PIXEL_SIZE) > 1e-12:
        raise ValueError(f"{vc}: the tracked pixels must be the data's {PIXEL_SIZE} m")
    folder.mkdir(parents=True, exist_ok=True)
    exact_path, video_path = folder / f"{vc.stem}_exact.h5", folder / f"{vc.stem}.mp4"
    empty_path, tracked_path = folder / f"{vc.stem}_empty.png", folder / f"{vc.stem}_tracked.h5"
    masks, weights = K.exact_masks(rec["x"], times, rec["spacing"], data_cam, scene)
    params = parameter_sets(case)[vc.set_index]
    source = dict(generator="experiments.reference (independent numpy/numba MLS-MPM)", dx=rec["dx"],
                  steps=rec["steps"], wall_s=round(rec["wall_s"], 1), render="exact masks at the video's frame times",
                  fps=vc.fps, pixel_size=data_cam.pixel_size, seed=vc.set_index)
    write(exact_path, masks, times, data_cam, scene.spec, weights, source,
          dict(params, kappa=scene.kappa, rho=scene.density))
    look = K.Look(seed=vc.seed)
    with C.Timer() as t_render:
        frames, empty = K.render_video(rec["x"], times, rec["spacing"], cam, scene, look)
        K.write_video(video_path, frames, vc.fps)
        K.write_png(empty_path, empty)
    scene_path = SCENES_DIR / f"{vc.case}.json"

    def track(video, empty_photo, out, options):
        jaxfoam_cli(["track", video, "--out", out, "--scene", scene_path, "--pixel-size", vc.pixel_size,
                     "--origin", cam.origin[0], cam.origin[1], "--background", empty_photo,
                     "--downsample", vc.downsample] + options)
        return read_silhouettes(out)

    exact = read_silhouettes(exact_path)
    with C.Timer() as t_track:
        tracked = track(video_path, empty_path, tracked_path, TRACK_OPTIONS)
    ious = iou_per_frame(tracked, exact)
    ablation = []
    if not quick:  # what each tracker option does on this video, and a rounder rim (another look)
        WORK.mkdir(parents=True, exist_ok=True)
        for label, opts in ABLATION:
            a = iou_per_frame(track(video_path, empty_path, WORK / f"{vc.stem}_ablation.h5", opts), exact)
            ablation.append([label, "this video", f"{a.min():.4f}", f"{a.mean():.4f}"])
        ablation.append([" ".join(map(str, TRACK_OPTIONS)) + " (the result above)", "this video",
                         f"{ious.min():.4f}", f"{ious.mean():.4f}"])
        for rim in OTHER_RIMS:
            f2, e2 = K.render_video(rec["x"], times, rec["spacing"], cam, scene, K.Look(seed=vc.seed, rim=rim))
            v2, p2 = K.write_video(WORK / f"{vc.stem}_rim.mp4", f2, vc.fps), K.write_png(WORK / f"{vc.stem}_rim.png", e2)
            a = iou_per_frame(track(v2, p2, WORK / f"{vc.stem}_rim.h5", TRACK_OPTIONS), exact)
            ablation.append([" ".join(map(str, TRACK_OPTIONS)), (f"rim radius {rim * 1e3:g} mm (this video: "
                             f"{look.rim * 1e3:g} mm)"), f"{a.min():.4f}", f"{a.mean():.4f}"])
    area = np.asarray(tracked.masks, float).sum(axis=(1, 2)) - np.asarray(exact.masks, float).sum(axis=(1, 2))
    progress(f"{vc.stem}: {len(times)} frames, IoU min {ious.min():.4f} mean {ious.mean():.4f}")
    return dict(vc=vc, frames=len(times), shape=cam.shape, times=times, ious=ious, area_diff=area,
                exact_area=np.asarray(exact.masks, float).sum(axis=(1, 2)),
                tracked_times=np.asarray(tracked.times), video=video_path, exact=exact_path, tracked=tracked_path,
                size_kB=video_path.stat().st_size / 1024, rec=rec, render_s=t_render.seconds, track_s=t_track.seconds,
                frame=frames[len(frames) // 2], mask=np.asarray(tracked.masks[len(frames) // 2]),
                exact_mask=np.asarray(exact.masks[len(frames) // 2]), truth=params, ablation=ablation)


def fit(data_path, folder, progress=print):
    """`jaxfoam fit DATA --out <folder>/<stem>_fit.json` with every default (resumes its log in out/)."""
    out = folder / f"{data_path.stem}_fit.json"
    if out.exists():
        return json.loads(out.read_text()), None
    WORK.mkdir(parents=True, exist_ok=True)
    log = WORK / f"{data_path.stem}.fitlog.h5"
    progress(f"fitting {data_path.name} (log {log})")
    wall = jaxfoam_cli(["fit", data_path, "--out", out, "--log", log] + (["--resume"] if log.exists() else []),
                       log=WORK / f"{data_path.stem}.fit.txt")
    return json.loads(out.read_text()), wall


def exact_loss_at(data_path, params):
    """The default fit's loss on a silhouette file at the material parameters `params` (its own grid)."""
    from fitting import FitSettings, build_problem, read_silhouettes

    problem = build_problem(read_silhouettes(data_path), FitSettings())
    return float(problem.loss(problem.transform.to_unconstrained({n: float(params[n])
                                                                   for n in problem.transform.names})))


def fit_rows(exact_fit, tracked_fit, truth):
    """Table rows: per parameter the truth, both fits, the exact fit's intervals, inside or not."""
    rows, inside = [], {}
    for n in exact_fit["fitted"]:
        a, b = exact_fit["params"][n], tracked_fit["params"][n]
        lo, hi = exact_fit["interval"][n]
        llo, lhi = exact_fit["interval_local"][n]
        inside[n] = (lo <= b <= hi, llo <= b <= lhi)
        rows.append([n, f"{truth[n]:.4g}", f"{a:.4g}", f"[{lo:.4g}, {hi:.4g}]", f"[{llo:.4g}, {lhi:.4g}]", f"{b:.4g}",
                     f"{100 * (b / a - 1):+.1f}%", "yes" if inside[n][0] else "NO", "yes" if inside[n][1] else "NO"])
    return rows, inside


def picture(results, quick):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(9, 3.8 * len(results)), squeeze=False)
    for row, r in zip(axes, results):
        vc = r["vc"]
        H, W = r["shape"]
        ext = [0, W * vc.pixel_size * 100, 0, H * vc.pixel_size * 100]
        k = len(r["times"]) // 2
        row[0].imshow(r["frame"], extent=ext)
        row[0].set_title(f"{vc.case} set {vc.set_index}: video frame {k} (t = {r['times'][k]:.3f} s), "
                         f"{vc.fps:g} fps H.264", fontsize=8)
        both = np.zeros(r["mask"].shape + (3,))
        m, e = r["mask"].astype(bool), r["exact_mask"].astype(bool)
        both[m & e] = (1, 1, 1)
        both[m & ~e] = (1, 0.2, 0.2)
        both[~m & e] = (0.2, 0.5, 1)
        row[1].imshow(both, extent=ext, interpolation="nearest")
        row[1].set_title(f"tracked mask (2.5 mm pixels), IoU {r['ious'][k]:.3f}\nred: tracked only, "
                         f"blue: exact only", fontsize=8)
        rows, cols = np.nonzero(e)  # zoom on the foam: the picture is about its edge
        p = vc.pixel_size * vc.downsample * 100
        for ax in row:
            ax.set_xlim(max(0, cols.min() - 8) * p, min(W // vc.downsample, cols.max() + 9) * p)
            ax.set_ylim(max(0, m.shape[0] - rows.max() - 9) * p, min(m.shape[0], m.shape[0] - rows.min() + 8) * p)
            ax.set_xlabel("x (cm, from the image's left)")
        row[0].set_ylabel("y (cm)")
    fig.tight_layout()
    C.save_fig(fig, NAME, quick)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse run, first frames, no fits (minutes)")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    folder = C.RESULTS / (NAME + ("_quick" if args.quick else ""))
    results, sections = [], []
    for vc in QUICK if args.quick else FULL:
        r = film(vc, args.quick, folder)
        results.append(r)
        rec, ious = r["rec"], r["ious"]
        lines = [f"## {vc.case} set {vc.set_index}", "",
                 C.md_table(["fps", "codec", "frames", "video pixels", "video pixel (mm)", "tracked pixel (mm)",
                             "video kB", "IoU min", "IoU mean", f"frames with IoU >= {IOU_GOAL}"],
                            [[f"{vc.fps:g}", "H.264 (libx264, yuv420p, crf 25)", r["frames"],
                              f"{r['shape'][1]} x {r['shape'][0]}", vc.pixel_size * 1e3,
                              vc.pixel_size * vc.downsample * 1e3, f"{r['size_kB']:.0f}", f"{ious.min():.4f}",
                              f"{ious.mean():.4f}", f"{int(np.sum(ious >= IOU_GOAL))} of {len(ious)}"]]),
                 "IoU per frame: " + ", ".join(f"{t:.3f} s {v:.4f}" for t, v in zip(r["times"], ious)) + ".", "",
                 (f"IoU goal ({IOU_GOAL}) met in every frame: {'yes' if ious.min() >= IOU_GOAL else 'NO'}. Tracked "
                  f"minus exact foam area: {np.mean(r['area_diff']):+.1f} pixels per frame on average (range "
                  f"{np.min(r['area_diff']):+.0f} to {np.max(r['area_diff']):+.0f}; the exact masks hold "
                  f"{np.mean(r['exact_area']):.0f} pixels)."), "",
                 *([C.md_table(["tracker options (besides the empty-scene photo)", "video", "IoU min", "IoU mean"],
                               r["ablation"]), ""] if r["ablation"] else []),
                 (f"Reference run: dx {rec['dx'] * 1e3:.3g} mm, {rec['steps']} steps, {rec['wall_s']:.0f} s"
                  f"{' (cached recording)' if rec.get('cached') else ''}; rendering and encoding "
                  f"{r['render_s']:.0f} s, `jaxfoam track` {r['track_s']:.0f} s."), ""]
        if not args.quick:
            exact_fit, _ = fit(r["exact"], folder)
            tracked_fit, _ = fit(r["tracked"], folder)
            rows, inside = fit_rows(exact_fit, tracked_fit, r["truth"])
            cross = exact_loss_at(r["exact"], tracked_fit["params"])
            from fitting import DEFAULT_BOUNDS
            at_bounds = sum(tuple(exact_fit["interval"][n]) == tuple(DEFAULT_BOUNDS[n]) for n in inside)
            n_in = sum(v[0] for v in inside.values())
            n_loc = sum(v[1] for v in inside.values())
            lines += [(f"Fits (`jaxfoam fit DATA --out FIT.json`, every default): tracked-fit value inside the "
                      f"exact fit's reported 95% interval for {n_in} of {len(inside)} parameters, inside its "
                      f"interval at the optimum (`interval_local`) for {n_loc} of {len(inside)}; the exact fit's "
                      f"reported interval is the default bounds for {at_bounds} of them (the check then says "
                      f"nothing: the fit does not reproduce the data, so the fitter reports the bounds). Exact fit: "
                      f"reproduces the data {exact_fit['reproduces_data']}, loss {exact_fit['loss']:.4g}, "
                      f"{exact_fit['wall_time'] / 60:.1f} min; tracked fit: reproduces the data "
                      f"{tracked_fit['reproduces_data']}, loss {tracked_fit['loss']:.4g}, "
                      f"{tracked_fit['wall_time'] / 60:.1f} min. The exact masks' loss at the tracked fit's "
                      f"parameters: {cross:.4g} (at the exact fit's: {exact_fit['loss']:.4g}; at the truth: "
                      f"{exact_loss_at(r['exact'], r['truth']):.4g})."), "",
                      C.md_table(["param", "truth", "exact fit", "exact 95% interval", "exact interval_local",
                                  "tracked fit", "tracked / exact - 1", "inside interval", "inside interval_local"],
                                 rows)]
        sections.append("\n".join(lines))
    picture(results, args.quick)
    body = (__doc__.split("\n\n")[1] + "\n\n" + "\n\n".join(sections)
            + f"\n\nFiles: `{os.path.relpath(folder, ROOT)}/` (video, empty-scene photo, silhouette files"
              f"{'' if args.quick else ', fit results'}).\n")
    C.write_md(NAME, args.quick, "End to end from video: tracked silhouettes and fits", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
