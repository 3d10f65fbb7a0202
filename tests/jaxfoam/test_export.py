"""`jaxfoam export` and `jaxfoam render --surface`.

Contracts checked: particle clouds read back by an independent reader (the PLY header parsed by hand,
trimesh) hold every per-particle field exactly; a resting block's mesh is closed (watertight) and
encloses the block's volume within 3%, its 2D outline the rectangle's area within 3%; bad input is
refused before any file is written, naming the field, the value and the allowed range; a missing
extra is named; `render --surface` writes a picture of the stated size whose foam is shaded.
"""
import json
import re

import numpy as np
import pytest
from helpers import scene

import jaxfoam
from jaxfoam import _surface, cli
from jaxfoam.export import export_trajectory, parse_frames
from jaxfoam.guards import EXPORT_HINT, require_extra

trimesh = pytest.importorskip("trimesh")
# The zoo's slump domain starts at -0.12 m; at its CLI default dx (0.24 m / 32 cells) and 8 particles
# per cell the particle lattice has a 3.75 mm pitch, so these 8 x 6 x 4 cm faces fall on lattice
# planes and the particles' volume is the block's.
DX = {2: 0.24 / 64, 3: 0.24 / 32}
BLOCK = {3: ([-0.0375, 0.0, -0.01875], [0.0425, 0.06, 0.02125]), 2: ([-0.0375, 0.0], [0.0425, 0.06])}


def block_trajectory(dim, frames=2, dtype=np.float64, shift=0.01):
    """A resting block (frame 0) and the same block moved up by `shift` m per later frame, with
    random fields of the trajectory's kinds."""
    lo, hi = BLOCK[dim]
    spec = scene("slump", dim, initial_shape={"type": "box", "min": lo, "max": hi})
    pts, _ = jaxfoam.sample_particles(jaxfoam.load_scene(spec), DX[dim])
    n, rng = len(pts), np.random.default_rng(1)
    x = np.repeat(pts[None], frames, 0)
    x[:, :, 1] += shift * np.arange(frames)[:, None]
    active = np.ones((frames, n), bool)
    active[1:, :5] = False  # slots that hold no material point are not exported
    f = {"x": x.astype(dtype), "v": rng.normal(size=(frames, n, dim)).astype(dtype),
         "gamma_dot": rng.exponential(size=(frames, n)).astype(dtype),
         "s": rng.uniform(0, 60, (frames, n)).astype(dtype), "J": np.ones((frames, n), dtype), "active": active}
    params = jaxfoam.Params(mu=200.0, kappa=3000.0, sigma_y=40.0, eta=10.0, m=0.5, rho=80.0)
    return {"frames": f, "times": 0.05 * np.arange(frames), "params": params, "scene": spec, "dx": DX[dim],
            "dt": 1e-4, "substeps": 10, "ppc": jaxfoam.DEFAULT_PPC[dim]}


def read_ply_by_hand(path):
    """A binary little-endian PLY's first element as a structured array, from its header alone."""
    with open(path, "rb") as f:
        raw = f.read()
    head, body = raw.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "double": "<f8", "uint": "<u4", "uchar": "u1", "int": "<i4"}
    count = next(int(ln.split()[2]) for ln in lines if ln.startswith("element vertex"))
    props = [ln.split() for ln in lines if ln.startswith("property")]
    return np.frombuffer(body, dtype=[(p[2], types[p[1]]) for p in props], count=count)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_particle_clouds_hold_every_field_exactly(tmp_path, dtype):
    parts = block_trajectory(3, dtype=dtype)
    export_trajectory(parts, tmp_path, surface=False)
    f = parts["frames"]
    for k in (0, 1):
        table = read_ply_by_hand(tmp_path / f"particles_{k:04d}.ply")
        a = f["active"][k]
        assert len(table) == a.sum()
        np.testing.assert_array_equal(table["id"], np.nonzero(a)[0])
        for i, axis in enumerate("xyz"):
            assert table[axis].dtype == dtype
            np.testing.assert_array_equal(table[axis], f["x"][k][a][:, i])
            np.testing.assert_array_equal(table["v" + axis], f["v"][k][a][:, i])
        for name in ("gamma_dot", "s", "J"):
            np.testing.assert_array_equal(table[name], f[name][k][a])
    cloud = trimesh.load(tmp_path / "particles_0001.ply")  # a second, independent reader
    np.testing.assert_allclose(cloud.vertices, f["x"][1][f["active"][1]], rtol=0, atol=0)


def test_2d_particle_clouds_have_z_zero_and_two_velocity_components(tmp_path):
    parts = block_trajectory(2)
    export_trajectory(parts, tmp_path, fmt="csv", frames="0")
    table = read_ply_by_hand(tmp_path / "particles_0000.ply")
    assert "vz" not in table.dtype.names and np.all(table["z"] == 0)
    np.testing.assert_array_equal(table["vy"], parts["frames"]["v"][0][:, 1])


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_resting_block_mesh_is_closed_and_holds_the_blocks_volume(tmp_path, fmt):
    parts = block_trajectory(3)
    manifest = export_trajectory(parts, tmp_path, fmt=fmt, particles=False)
    lo, hi = (np.asarray(b) for b in BLOCK[3])
    volume = float(np.prod(hi - lo))
    spacing = _surface.particle_spacing(DX[3], 8, 3)
    for k, entry in enumerate(manifest["frames"]):
        mesh = trimesh.load(tmp_path / entry["surface"], process=True)  # merges the OBJ's split vertices
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert abs(mesh.volume / volume - 1) < 0.03, mesh.volume / volume - 1
        assert mesh.volume > 0  # faces wind outward
        np.testing.assert_allclose(entry["enclosed_volume_m3"], mesh.volume, rtol=1e-5)
        shift = np.array([0.0, 0.01 * k, 0.0])
        # Faces at the block's faces: the mesh's extent within half a particle spacing of the block's.
        np.testing.assert_allclose(mesh.bounds, [lo + shift, hi + shift], atol=0.5 * spacing)


def test_iso_level_puts_a_flat_face_at_the_blocks_face():
    parts = block_trajectory(3)
    x, vol, spacing = _surface.frame_particles(jaxfoam._trajectory.as_saved_trajectory(parts), 0)
    field = _surface.volume_field(x, vol, spacing)
    hi = BLOCK[3][1]
    # The field averaged over the middle of the top face, along y: it crosses ISO_LEVEL at the face.
    xs, ys, zs = (field.nodes(k) for k in range(3))
    mid = np.ix_(np.abs(xs - 0.005) < 0.02, np.arange(len(ys)), np.abs(zs - 0.00125) < 0.01)
    profile = field.values[mid].mean(axis=(0, 2))
    i = np.nonzero((ys > 0.03) & (profile < _surface.ISO_LEVEL))[0][0]
    y_face = np.interp(_surface.ISO_LEVEL, profile[[i, i - 1]], ys[[i, i - 1]])
    assert abs(y_face - hi[1]) < 0.1 * spacing


@pytest.mark.parametrize("fmt", ["obj", "csv", "svg", "ply"])
def test_2d_outline_encloses_the_rectangles_area(tmp_path, fmt):
    parts = block_trajectory(2, frames=1)
    manifest = export_trajectory(parts, tmp_path, fmt=fmt, particles=False)
    lo, hi = (np.asarray(b) for b in BLOCK[2])
    area = float(np.prod(hi - lo))
    path = tmp_path / manifest["frames"][0]["surface"]
    if fmt == "obj":
        text = path.read_text().splitlines()
        verts = np.array([[float(v) for v in ln.split()[1:3]] for ln in text if ln.startswith("v ")])
        loops = [verts[np.array(ln.split()[1:-1], int) - 1] for ln in text if ln.startswith("l ")]
        assert all(ln.split()[1] == ln.split()[-1] for ln in text if ln.startswith("l "))  # closed
    elif fmt == "csv":
        rows = np.loadtxt(path, delimiter=",", skiprows=1)
        loops = [rows[rows[:, 0] == i, 1:] for i in np.unique(rows[:, 0])]
    elif fmt == "svg":
        d = re.search(r' d="([^"]+)"', path.read_text()).group(1)
        loops = [np.array([[float(v) for v in p.split(",")] for p in re.findall(r"[-\d.]+,[-\d.]+", seg)]) * 1e-3
                 for seg in d.split("Z") if seg.strip()]
        loops = [p * [1, -1] for p in loops]  # the page's y runs down
    else:
        mesh = trimesh.load(path, process=False)
        verts = np.asarray(mesh.vertices)[:, :2]
        loops = [verts]  # one loop, its vertices in order
        assert np.all(np.asarray(mesh.vertices)[:, 2] == 0)
    got = sum(_surface.signed_area(p) for p in loops)
    assert abs(got / area - 1) < 0.03, got / area - 1
    assert abs(manifest["frames"][0]["enclosed_area_m2"] / area - 1) < 0.03


def test_frame_selection_and_its_errors():
    np.testing.assert_array_equal(parse_frames("all", 5), range(5))
    np.testing.assert_array_equal(parse_frames("0,-1", 5), [0, 4])
    np.testing.assert_array_equal(parse_frames("1:5:2", 5), [1, 3])
    with pytest.raises(ValueError, match=r"--frames: frame 5 is out of range \(this trajectory has 5 frames: "
                                         r"indices 0 to 4, or -5 to -1"):
        parse_frames("0,5", 5)
    with pytest.raises(ValueError, match="range '2:9' reaches frame 9, out of range"):
        parse_frames("2:9", 5)
    with pytest.raises(ValueError, match="'x' is not a frame index or a range"):
        parse_frames("x", 5)


def test_bad_input_is_refused_before_any_file_is_written(tmp_path, capsys):
    h5 = jaxfoam.save_trajectory(tmp_path / "t.h5", block_trajectory(3))
    out = tmp_path / "out"
    cases = [(["export", str(tmp_path / "none.h5"), "--out", str(out)], "trajectory file '.*none.h5' does not exist"),
             (["export", h5, "--out", str(out), "--format", "stl"], "--format must be one of ply, obj, svg, csv, got 'stl'"),
             (["export", h5, "--out", str(out), "--format", "svg"], "a 3D trajectory's surface is written as ply or obj"),
             (["export", h5, "--out", str(out), "--frames", "0,2"], "--frames: frame 2 is out of range"),
             (["export", h5, "--out", h5], "--out '.*t.h5' is a file; give a folder"),
             (["render", h5, "--out", str(out / "x.png"), "--camera", "0,20"], "--camera sets the view of --surface")]
    for argv, message in cases:
        assert cli.main(argv) == 2, argv
        assert re.search(message, capsys.readouterr().err), argv
        assert not out.exists()


def test_a_missing_extra_is_named():
    with pytest.raises(ImportError, match=re.escape("needs no_such_module: install the export extra: "
                                                    "pip install -e '.[export]'")):
        require_extra("jaxfoam export", "no_such_module", hint=EXPORT_HINT)


def test_export_command_writes_the_frames_asked_for_and_nothing_half_written(tmp_path, capsys):
    h5 = jaxfoam.save_trajectory(tmp_path / "t.h5", block_trajectory(2, frames=3))
    out = tmp_path / "out"
    assert cli.main(["export", h5, "--out", str(out), "--format", "svg", "--frames", "0,-1"]) == 0
    manifest = json.loads((out / "export.json").read_text())
    assert [e["index"] for e in manifest["frames"]] == [0, 2]
    assert sorted(p.name for p in out.iterdir()) == ["export.json", "particles_0000.ply", "particles_0002.ply",
                                                      "surface_0000.svg", "surface_0002.svg"]
    np.testing.assert_allclose([e["time_s"] for e in manifest["frames"]], [0.0, 0.1])


@pytest.mark.parametrize("dim", [3, 2])
def test_render_surface_writes_a_shaded_picture_of_the_stated_size(tmp_path, dim):
    import matplotlib.image as mpimg

    from jaxfoam import _raster, render

    parts = block_trajectory(dim, frames=2)
    h5 = jaxfoam.save_trajectory(tmp_path / "t.h5", parts)
    png = tmp_path / "s.png"
    argv = ["render", h5, "--out", str(png), "--surface", "--panels", "2"] + (["--camera", "35,20"] if dim == 3 else [])
    assert cli.main(argv) == 0
    img = mpimg.imread(png)[..., :3]
    traj = jaxfoam.load_trajectory(h5)
    view = _raster.View(traj, np.arange(2), render.SURFACE_PANEL_PX,
                        camera=_raster.Camera(35, 20) if dim == 3 else None)
    assert img.shape == (render.HEADER_PX + view.height + render.TITLE_PX + render.GAP_PX,
                         2 * (view.width + render.GAP_PX) + render.GAP_PX, 3)
    # The second panel, where figimage put it: its foam pixels carry many grey levels (shading).
    rgb, foam = view.frame(1)
    x0, y0 = 2 * render.GAP_PX + view.width, render.HEADER_PX + render.TITLE_PX
    panel = np.round(img[y0:y0 + view.height, x0:x0 + view.width] * 255)
    np.testing.assert_array_equal(panel, rgb)
    grey = panel[foam > 0.99].mean(-1)
    assert (foam > 0.99).sum() > 2000
    assert len(np.unique(np.round(grey))) > 20 and np.ptp(grey) > 40


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # the ffmpeg reader's subprocess
def test_surface_video_has_one_frame_per_trajectory_frame(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    from jaxfoam.render import render_surface_video

    out = render_surface_video(block_trajectory(2, frames=3), tmp_path / "v.mp4", fps=10, width_px=200,
                               frames_dir=tmp_path / "png")
    with imageio.get_reader(out) as r:
        frames = [f for f in r]  # the reader reports an infinite length, which list() would use
    assert len(frames) == 3 and frames[0].shape[1] == 208 and frames[0].shape[0] % 16 == 0
    # frames_dir: one PNG per frame, of the video's size
    pngs = sorted((tmp_path / "png").glob("frame_*.png"))
    assert [p.name for p in pngs] == ["frame_000.png", "frame_001.png", "frame_002.png"]
    assert imageio.imread(pngs[-1]).shape[:2] == frames[0].shape[:2]


@pytest.mark.parametrize("dim", [3, 2])
def test_surface_render_draws_an_sdf_collider_where_its_phi_is_negative(dim):
    """Contract of `colliders=`: a sphere collider beside the block is drawn in COLLIDER_RGB's shades,
    its projected area that of its disc within 10% (3D: marching cubes of phi; 2D: phi < 0 per pixel),
    and the foam's pixels are unchanged away from it."""
    from jaxfoam import _raster, render
    from jaxfoam.sdf import collider_from_spec

    # Frame 1 (the block 5 cm higher) widens the view; frame 0 leaves room above the block for the sphere.
    saved = jaxfoam._trajectory.as_saved_trajectory(block_trajectory(dim, frames=2, shift=0.05))
    r, centre = 0.015, [0.0025, 0.085] + ([0.00125] if dim == 3 else [])
    sphere = collider_from_spec({"shape": {"type": "sphere", "center": centre, "radius": r}})
    cam = _raster.Camera(0.0, 0.0) if dim == 3 else None  # looking along z: the sphere's disc is a circle
    plain = _raster.View(saved, np.arange(2), render.SURFACE_PANEL_PX, camera=cam)
    view = _raster.View(saved, np.arange(2), render.SURFACE_PANEL_PX, camera=cam, colliders=(sphere,))
    rgb0, foam0 = plain.frame(0)
    rgb, foam = view.frame(0)
    # Collider pixels: the colour changed from the plain render and is a shade of COLLIDER_RGB.
    col = np.asarray(_raster.COLLIDER_RGB)
    changed = np.any(rgb.astype(int) != rgb0.astype(int), axis=-1) & (foam < 0.01)
    px = rgb[changed].astype(float)
    ratio = px / np.maximum(px.sum(-1, keepdims=True), 1e-9)
    shade_of = np.all(np.abs(ratio - col / col.sum()) < 0.03, axis=-1)
    area_m2 = shade_of.sum() / view.scale ** 2
    assert abs(area_m2 / (np.pi * r ** 2) - 1) < 0.10, area_m2 / (np.pi * r ** 2)
    # The foam is where it was (the sphere is above the block, not in front of it).
    np.testing.assert_allclose(foam.sum(), foam0.sum(), rtol=1e-6)
