"""Pictures of a simulation: a contact sheet of frames (PNG) and a video (MP4).

Particles are drawn as dots coloured by the plastic strain rate gamma_dot (1/s, log scale) or the
deviatoric stress magnitude s (Pa), with the domain box, the floor and the plates at their position
at each frame's time. 3D trajectories are drawn as the x-y projection seen by the camera of the
silhouette spec (looking along -z: nearer particles, larger z, are drawn on top).

Needs the `viz` extra (matplotlib; imageio and imageio-ffmpeg for video). Figures are drawn with
matplotlib's Agg canvas directly, so importing this module never changes the pyplot backend.
"""
from __future__ import annotations

import math
import os

import numpy as np

from .guards import VIZ_HINT, atomic_output
from ._trajectory import SavedTrajectory, as_saved_trajectory
from .video import ffmpeg_subprocess

COLOR_FIELDS = ("gamma_dot", "s")
# Plastic rates below this fraction of the colour scale's top are drawn grey (elastic or nearly so):
# four decades span creeping flow (~1e-3 1/s) to splashes (~10 1/s).
GAMMA_DECADES = 4.0
# Colour scales use this upper percentile of the shown values, so one outlier particle does not wash
# out the rest.
COLOR_PERCENTILE = 99.5
# Default particles per cell when the file does not say (2D, 3D): the sampling defaults of load_scene.
DEFAULT_PPC = {2: 4, 3: 8}
# Dots are drawn this fraction of the mean particle spacing wide: large enough to read as a continuum.
DOT_FRACTION = 1.5
# Grey for elastic particles (gamma_dot below the colour scale), the floor, and the plates.
ELASTIC_GREY = "#b8b8b8"
FLOOR_GREY = "#8c8c8c"
PLATE_COLOR = "#5b4636"


def _require_matplotlib():
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise ImportError(f"jaxfoam.render needs matplotlib: {VIZ_HINT}") from exc


def _frame_indices(num_frames: int, n_frames: int) -> np.ndarray:
    """n_frames indices evenly spread over [0, num_frames - 1], first and last included."""
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    return np.unique(np.round(np.linspace(0, num_frames - 1, min(n_frames, num_frames))).astype(int))


class _Style:
    """Colour scale, geometry and dot size shared by every panel of one picture."""

    def __init__(self, traj: SavedTrajectory, color: str, indices, vmin=None, vmax=None):
        from matplotlib import colormaps, colors

        if color not in COLOR_FIELDS:
            raise ValueError(f"color must be one of {COLOR_FIELDS}, got {color!r}")
        if color not in traj.frames:
            raise ValueError(f"this trajectory has no per-particle field '{color}' "
                             f"(it holds {sorted(traj.frames)})")
        self.traj, self.color = traj, color
        self.scene = traj.scene
        active = traj.frames["active"][indices]
        vals = np.asarray(traj.frames[color][indices], np.float64)[active]
        vals = vals[np.isfinite(vals)]
        top = float(np.percentile(vals, COLOR_PERCENTILE)) if vals.size else 0.0
        if color == "gamma_dot":
            hi = vmax if vmax is not None else (top if top > 0 else 1.0)
            lo = vmin if vmin is not None else hi * 10.0 ** (-GAMMA_DECADES)
            self.norm = colors.LogNorm(vmin=lo, vmax=hi)
            self.cmap = colormaps["plasma"].with_extremes(under=ELASTIC_GREY)
            self.label = "plastic strain rate $\\dot\\gamma$ (1/s, log scale; grey: below scale or elastic)"
            self.extend = "min"
        else:
            hi = vmax if vmax is not None else (top if top > 0 else 1.0)
            self.norm = colors.Normalize(vmin=0.0 if vmin is None else vmin, vmax=hi)
            self.cmap = colormaps["viridis"]
            self.label = "deviatoric stress $\\|s\\|$ (Pa)"
            self.extend = "max"
        self.lo = np.asarray(self.scene.domain_min, float)
        self.hi = np.asarray(self.scene.domain_max, float)
        floor = self.scene.floor_y
        # Show a strip below the floor (or the domain bottom) so the floor is visible.
        self.margin = 0.04 * float(self.hi[1] - self.lo[1])
        ybottom = min(self.lo[1], floor if floor is not None else self.lo[1]) - self.margin
        self.xlim = (float(self.lo[0]), float(self.hi[0]))
        self.ylim = (float(ybottom), float(self.hi[1]))
        d = traj.dim
        ppc = traj.ppc or DEFAULT_PPC[d]
        self.spacing = traj.dx / ppc ** (1.0 / d)

    def values(self, k: int):
        """Active particles of frame k, as (xy (n, 2) m, colour values (n,)), sorted far to near in 3D."""
        x = np.asarray(self.traj.frames["x"][k], np.float64)
        c = np.asarray(self.traj.frames[self.color][k], np.float64)
        a = np.asarray(self.traj.frames["active"][k], bool)
        x, c = x[a], c[a]
        if x.shape[1] == 3:
            # The camera looks along -z: particles with larger z are nearer and drawn last.
            order = np.argsort(x[:, 2], kind="stable")
            x, c = x[order], c[order]
        if self.color == "gamma_dot":
            c = np.where(c > 0, c, self.norm.vmin * 0.5)  # zero rate -> below scale -> grey
        return x[:, :2], c

    def dot_size(self, ax) -> float:
        """Marker area in points^2 for dots DOT_FRACTION of the particle spacing wide on this axes."""
        fig = ax.figure
        width_in = ax.get_position().width * fig.get_figwidth()
        height_in = ax.get_position().height * fig.get_figheight()
        pts_per_m = 72.0 * min(width_in / (self.xlim[1] - self.xlim[0]), height_in / (self.ylim[1] - self.ylim[0]))
        return max((DOT_FRACTION * self.spacing * pts_per_m) ** 2, 0.05)

    def draw_static(self, ax):
        """Domain box and floor (do not move)."""
        from matplotlib.patches import Rectangle

        ax.set_xlim(*self.xlim)
        ax.set_ylim(*self.ylim)
        ax.set_aspect("equal")
        ax.add_patch(Rectangle(tuple(self.lo[:2]), *(self.hi[:2] - self.lo[:2]), fill=False, lw=0.8,
                               ec="#555555", ls="--", zorder=1))
        floor = self.scene.floor_y
        if floor is not None:
            ax.add_patch(Rectangle((self.xlim[0], self.ylim[0]), self.xlim[1] - self.xlim[0], floor - self.ylim[0],
                                   fc=FLOOR_GREY, ec="none", hatch="////", alpha=0.6, zorder=4))
            ax.axhline(floor, color="#333333", lw=1.0, zorder=4)
        ax.tick_params(labelsize=7)

    def plate_rects(self, t: float):
        """Per plate: lower-left corner (2,) m and size (2,) m at time t (s), in the x-y projection."""
        out = []
        for plate in self.scene.plates:
            c = np.asarray(plate.position(t), np.float64)
            h = np.asarray(plate.half_size, np.float64)
            out.append(((c[0] - h[0], c[1] - h[1]), (2 * h[0], 2 * h[1])))
        return out

    def draw_plates(self, ax, t: float):
        from matplotlib.patches import Rectangle

        return [ax.add_patch(Rectangle(xy, w, h, fc=PLATE_COLOR, ec="black", lw=0.6, zorder=5))
                for xy, (w, h) in self.plate_rects(t)]

    def title(self) -> str:
        p = self.traj.params
        spec = self.scene.spec
        name = spec.get("name", self.scene.kind)
        return (f"{name} ({self.traj.dim}D{', x-y projection' if self.traj.dim == 3 else ''}): "
                f"$\\mu$ = {p.mu:.4g} Pa, $\\sigma_Y$ = {p.sigma_y:.4g} Pa, $\\eta$ = {p.eta:.4g} Pa s$^m$, "
                f"m = {p.m:.3g}, $\\kappa$ = {p.kappa:.4g} Pa, $\\rho$ = {p.rho:.4g} kg/m$^3$; "
                f"dx = {self.traj.dx * 1e3:.3g} mm, {int(self.traj.frames['active'][0].sum())} particles")

    def colorbar(self, fig, axes):
        from matplotlib.cm import ScalarMappable

        sm = ScalarMappable(norm=self.norm, cmap=self.cmap)
        cb = fig.colorbar(sm, ax=axes, extend=self.extend, shrink=0.9, pad=0.02)
        cb.set_label(self.label, fontsize=8)
        cb.ax.tick_params(labelsize=7)
        if self.color == "s":
            s_yield = math.sqrt(2.0 / 3.0) * float(self.traj.params.sigma_y)
            if self.norm.vmin < s_yield < self.norm.vmax:
                cb.ax.axhline(s_yield, color="white", lw=1.5)
                cb.ax.text(0.5, s_yield, "yield", color="white", fontsize=6, ha="center", va="bottom",
                           transform=cb.ax.get_yaxis_transform())
        return cb


def render_contact_sheet(traj, out_png, n_frames: int = 8, color: str = "gamma_dot", ncols: int | None = None,
                         panel_width: float = 2.6, dpi: int = 130, vmin: float | None = None,
                         vmax: float | None = None) -> str:
    """Draw a grid of frames of a trajectory to a PNG; returns the path.

    Args:
      traj: a trajectory file path, a SavedTrajectory (`load_trajectory`) or a `jaxfoam.Trajectory`.
      out_png: output path.
      n_frames: number of panels (frames evenly spread from first to last).
      color: "gamma_dot" (plastic strain rate, 1/s, log scale) or "s" (deviatoric stress, Pa).
      ncols: panels per row (default: at most 4, rows as even as possible).  panel_width: inches.  dpi: resolution.
      vmin, vmax: colour scale limits (1/s or Pa; default: from the shown frames).
    """
    _require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    traj = as_saved_trajectory(traj)
    if traj.num_frames == 0:
        raise ValueError("the trajectory holds no frame to draw")
    idx = _frame_indices(traj.num_frames, int(n_frames))
    style = _Style(traj, color, idx, vmin, vmax)
    n = len(idx)
    # Default: at most 4 panels per row, rows filled as evenly as possible (5 -> 3 + 2, 8 -> 4 + 4).
    ncols = math.ceil(n / math.ceil(n / 4)) if ncols is None else max(1, int(ncols))
    nrows = math.ceil(n / ncols)
    aspect = (style.ylim[1] - style.ylim[0]) / (style.xlim[1] - style.xlim[0])
    fig = Figure(figsize=(ncols * panel_width + 1.4, nrows * panel_width * aspect + 0.9), dpi=dpi,
                 layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True, sharey=True)
    fig.suptitle(style.title(), fontsize=8)
    fig.get_layout_engine().execute(fig)  # settle panel sizes before sizing the dots
    used = []
    for ax, k in zip(axes.ravel(), idx):
        style.draw_static(ax)
        t = float(traj.times[k])
        xy, c = style.values(k)
        ax.scatter(xy[:, 0], xy[:, 1], c=c, s=style.dot_size(ax), cmap=style.cmap, norm=style.norm,
                   linewidths=0, zorder=3, rasterized=True)
        style.draw_plates(ax, t)
        ax.set_title(f"t = {t:.3f} s", fontsize=8)
        used.append(ax)
    for ax in axes.ravel()[n:]:
        ax.set_axis_off()
    for ax in axes[-1, :]:
        ax.set_xlabel("x (m)", fontsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("y (m)", fontsize=7)
    style.colorbar(fig, axes.ravel().tolist())
    with atomic_output(out_png) as tmp:  # a killed render never leaves half a picture
        fig.savefig(tmp, dpi=dpi)
    return os.fspath(out_png)


def _video_inputs(traj, fps):
    """The video writers' shared checks and imports: (imageio, FigureCanvasAgg, Figure, the saved
    trajectory, its frame indices). Raises ImportError naming the viz extra, ValueError on bad input."""
    _require_matplotlib()
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401
    except ImportError as exc:
        raise ImportError(f"render_video needs imageio and imageio-ffmpeg: {VIZ_HINT}") from exc
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not (isinstance(fps, (int, float)) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    traj = as_saved_trajectory(traj)
    if traj.num_frames == 0:
        raise ValueError("the trajectory holds no frame to draw")
    idx = np.arange(traj.num_frames)
    return imageio, FigureCanvasAgg, Figure, traj, idx


def render_video(traj, out_mp4, fps: int = 20, color: str = "gamma_dot", width_px: int = 800, dpi: int = 100,
                 vmin: float | None = None, vmax: float | None = None) -> str:
    """Write every frame of a trajectory to an MP4 video (H.264 via imageio-ffmpeg); returns the path.

    Args: traj (path, SavedTrajectory or Trajectory), out_mp4, fps (frames per second of video),
      color ("gamma_dot" 1/s or "s" Pa), width_px (video width in pixels, rounded to a multiple of 16),
      dpi, vmin/vmax (colour scale limits). Raises ImportError naming the viz extra when imageio or
      imageio-ffmpeg is missing.
    """
    imageio, FigureCanvasAgg, Figure, traj, idx = _video_inputs(traj, fps)
    style = _Style(traj, color, idx, vmin, vmax)
    aspect = (style.ylim[1] - style.ylim[0]) / (style.xlim[1] - style.xlim[0])
    # H.264 encoders want frame sizes divisible by 16 (imageio's macro block size).
    w_px = max(16, int(round(width_px / 16)) * 16)
    h_px = max(16, int(round(w_px * 0.82 * aspect / 16 + 0.5)) * 16)
    fig = Figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    ax = fig.subplots()
    fig.suptitle(style.title(), fontsize=7)
    style.draw_static(ax)
    ax.set_xlabel("x (m)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    style.colorbar(fig, ax)
    ax.set_title(f"t = {float(traj.times[0]):.3f} s", fontsize=8)  # reserve the title's room in the layout
    fig.get_layout_engine().execute(fig)
    xy, c = style.values(0)
    dots = ax.scatter(xy[:, 0], xy[:, 1], c=c, s=style.dot_size(ax), cmap=style.cmap, norm=style.norm,
                      linewidths=0, zorder=3)
    fig.set_layout_engine("none")  # freeze the layout: every video frame has the same geometry
    plates = style.draw_plates(ax, float(traj.times[0]))
    with ffmpeg_subprocess(), atomic_output(out_mp4) as tmp:
        with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=7,
                                macro_block_size=16) as writer:
            for k in idx:
                xy, c = style.values(k)
                dots.set_offsets(xy)
                dots.set_array(c)
                for patch, (corner, _) in zip(plates, style.plate_rects(float(traj.times[k]))):
                    patch.set_xy(corner)
                ax.set_title(f"t = {float(traj.times[k]):.3f} s", fontsize=8)
                canvas.draw()
                writer.append_data(np.asarray(canvas.buffer_rgba())[:, :, :3])
    return os.fspath(out_mp4)


# Shaded surface pictures (`render --surface`): panel and text bands of the sheet, pixels.
SURFACE_PANEL_PX = 400
HEADER_PX = 52
TITLE_PX = 22
GAP_PX = 8


def _surface_view(traj, indices, width_px, camera, multiple=1, colliders=()):
    from . import _raster
    from ._surface import require_skimage

    require_skimage()
    if camera is not None and not isinstance(camera, _raster.Camera):
        camera = _raster.Camera(*camera)
    return _raster.View(traj, indices, width_px, camera=camera, multiple=multiple, colliders=colliders)


def _surface_title(traj, view) -> str:
    p, spec = traj.params, traj.scene.spec
    cam = (f"; camera azimuth {view.camera.azimuth:g} deg, elevation {view.camera.elevation:g} deg"
           if traj.dim == 3 else "")
    return (f"{spec.get('name', traj.scene.kind)} ({traj.dim}D surface){cam}\n$\\mu$ = {p.mu:.4g} Pa, "
            f"$\\sigma_Y$ = {p.sigma_y:.4g} Pa, $\\eta$ = {p.eta:.4g} Pa s$^m$, m = {p.m:.3g}\n"
            f"dx = {traj.dx * 1e3:.3g} mm, {int(traj.frames['active'][0].sum())} particles; "
            f"bar: {view.scale_bar() * 100:g} cm")


def _with_scale_bar(rgb: np.ndarray, view) -> np.ndarray:
    """The panel with a black scale bar (view.scale_bar() m) at its lower left."""
    out = rgb.copy()
    n = round(view.scale_bar() * view.scale)
    y = view.height - 10
    out[y - 2:y + 1, 10:10 + n] = 0
    return out


def render_surface_sheet(traj, out_png, n_frames: int = 8, camera=None, ncols: int | None = None,
                         panel_px: int = SURFACE_PANEL_PX, dpi: int = 130, colliders=()) -> str:
    """Draw a grid of shaded surface renders (3D: lit mesh, floor, plates; 2D: the lit outline fill) to a
    PNG; returns the path.

    Args: traj (path, SavedTrajectory or Trajectory), out_png, n_frames (panels, evenly spread),
      camera ((azimuth, elevation) deg or a jaxfoam._raster.Camera; 3D only), ncols (default at most 4),
      panel_px (panel width, pixels), dpi (text size), colliders (`jaxfoam.sdf.SDFCollider`s of the run,
      drawn where their phi < 0). The picture is ncols (panel_px + GAP_PX) + GAP_PX pixels wide. Needs
      the viz and export extras (matplotlib, scikit-image).
    """
    _require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    traj = as_saved_trajectory(traj)
    if traj.num_frames == 0:
        raise ValueError("the trajectory holds no frame to draw")
    idx = _frame_indices(traj.num_frames, int(n_frames))
    view = _surface_view(traj, idx, int(panel_px), camera, colliders=colliders)
    n = len(idx)
    ncols = math.ceil(n / math.ceil(n / 4)) if ncols is None else max(1, int(ncols))
    nrows = math.ceil(n / ncols)
    cell_w, cell_h = view.width + GAP_PX, view.height + TITLE_PX
    W, H = ncols * cell_w + GAP_PX, HEADER_PX + nrows * cell_h + GAP_PX
    fig = Figure(figsize=(W / dpi, H / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.text(0.5, 1 - 6 / H, _surface_title(traj, view), ha="center", va="top", fontsize=7, linespacing=1.1)
    for i, k in enumerate(idx):
        r, c = divmod(i, ncols)
        rgb, _ = view.frame(int(k))
        if i == 0:
            rgb = _with_scale_bar(rgb, view)
        x0, top = GAP_PX + c * cell_w, HEADER_PX + r * cell_h + TITLE_PX
        fig.figimage(rgb, xo=x0, yo=H - top - view.height, origin="upper")
        fig.text((x0 + view.width / 2) / W, 1 - (top - 4) / H, f"t = {float(traj.times[k]):.3f} s",
                 ha="center", va="bottom", fontsize=8)
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=dpi)
    return os.fspath(out_png)


def render_surface_video(traj, out_mp4, fps: int = 20, camera=None, width_px: int = 800, colliders=(),
                         frames_dir=None) -> str:
    """Write every frame's shaded surface render to an MP4 video (H.264); returns the path. The frame
    size is width_px rounded up to a multiple of 16 by the view's height (also a multiple of 16).
    colliders: as in `render_surface_sheet`; frames_dir: also write each frame there as frame_###.png."""
    imageio, FigureCanvasAgg, Figure, traj, idx = _video_inputs(traj, fps)
    view = _surface_view(traj, idx, int(width_px), camera, multiple=16, colliders=colliders)
    if frames_dir is not None:
        os.makedirs(frames_dir, exist_ok=True)
    fig = Figure(figsize=(view.width / 100, view.height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    image = fig.figimage(np.zeros((view.height, view.width, 3), np.uint8), origin="upper")
    label = fig.text(0.02, 0.97, "", ha="left", va="top", fontsize=9)
    with ffmpeg_subprocess(), atomic_output(out_mp4) as tmp, \
            imageio.get_writer(tmp, fps=fps, codec="libx264", quality=7, macro_block_size=16) as writer:
        for k in idx:
            image.set_data(_with_scale_bar(view.frame(int(k))[0], view))
            label.set_text(f"t = {float(traj.times[k]):.3f} s   (bar: {view.scale_bar() * 100:g} cm)")
            canvas.draw()
            rgb = np.asarray(canvas.buffer_rgba())[:, :, :3]
            writer.append_data(rgb)
            if frames_dir is not None:
                with atomic_output(os.path.join(frames_dir, f"frame_{int(k):03d}.png")) as tmp:
                    imageio.imwrite(tmp, rgb, format="png")
    return os.fspath(out_mp4)
