"""Trajectory files, pictures, the command line and the example scenes.

Contracts checked: a saved trajectory reads back bit-identical; files that are not jaxfoam
trajectories give a TrajectoryError naming the problem; `jaxfoam simulate` + `jaxfoam render` make a
trajectory and a PNG; plates are drawn where Plate.position(t) puts them and 3D particles in camera
depth order; every example scene loads and runs finite, and a drop's centre of mass moves with
v0 + g t before it touches anything (momentum balance).
"""
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import jaxfoam
from jaxfoam import cli
from jaxfoam._trajectory import TrajectoryWriter

REPO = Path(__file__).resolve().parents[2]
SCENES = sorted((REPO / "experiments" / "scenes").glob("*.json"))
# Tiny runs: 2 frames of 2 ms (a handful of substeps at these spacings).
TINY = dict(frames=2, duration=0.004)
TINY_DX = {2: 0.02, 3: 0.03}  # m
CLI_SCENE = REPO / "experiments" / "scenes" / "hanging_plate_2d.json"
CLI_DTYPE = "float32"


def _parts(dtype, T=3, N=50, dim=2, scene="drop_2d.json", seed=0):
    rng = np.random.default_rng(seed)
    frames = dict(x=rng.uniform(-0.1, 0.1, (T, N, dim)).astype(dtype), v=rng.normal(size=(T, N, dim)).astype(dtype),
                  gamma_dot=rng.exponential(1.0, (T, N)).astype(dtype), s=rng.uniform(0, 80, (T, N)).astype(dtype),
                  J=rng.uniform(0.9, 1.1, (T, N)).astype(dtype), active=rng.uniform(size=(T, N)) < 0.9)
    params = jaxfoam.Params(mu=200.0, kappa=3000.0, sigma_y=40.0, eta=10.0, m=0.5, rho=80.0)
    return dict(frames=frames, times=np.array([0.0, 0.1, 0.25])[:T], params=params,
                scene=(REPO / "experiments" / "scenes" / scene).read_text(), dx=0.005, dt=1.4e-4, substeps=711, ppc=4)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_round_trip_is_bit_identical(tmp_path, dtype):
    parts = _parts(dtype)
    path = jaxfoam.save_trajectory(tmp_path / "t.h5", parts, creator="test")
    back = jaxfoam.load_trajectory(path)
    assert set(back.frames) == set(parts["frames"])
    for k, a in parts["frames"].items():
        assert back.frames[k].dtype == a.dtype, k
        np.testing.assert_array_equal(back.frames[k], a, err_msg=k)
    np.testing.assert_array_equal(back.times, parts["times"])
    assert back.params == parts["params"]
    assert back.scene_json == parts["scene"]
    assert (back.dx, back.dt, back.substeps, back.ppc) == (0.005, 1.4e-4, 711, 4)
    assert back.dtype == np.dtype(dtype).name and back.version == jaxfoam.__version__ and back.complete
    assert back.created["creator"] == "test" and back.created["created"].endswith("+00:00")
    assert back.scene.kind == "drop" and back.dim == 2 and back.num_frames == 3 and back.num_particles == 50
    # Re-saving what was read gives the same content again.
    again = jaxfoam.load_trajectory(jaxfoam.save_trajectory(tmp_path / "t2.h5", back))
    np.testing.assert_array_equal(again.frames["x"], parts["frames"]["x"])


def test_save_accepts_simulate_trajectory_and_block_appends(tmp_path):
    parts = _parts(np.float64)
    scene = jaxfoam.load_scene(parts["scene"])
    traj = jaxfoam.Trajectory(frames=parts["frames"], times=parts["times"], final=None, dx=parts["dx"],
                              dt=parts["dt"], substeps=parts["substeps"], scene=scene, params=parts["params"])
    whole = jaxfoam.load_trajectory(jaxfoam.save_trajectory(tmp_path / "whole.h5", traj))
    with TrajectoryWriter(tmp_path / "blocks.h5", parts["params"], scene, parts["dx"], parts["dt"],
                          parts["substeps"]) as w:
        for k in range(3):
            w.append({n: a[k:k + 1] for n, a in parts["frames"].items()}, parts["times"][k:k + 1])
    blocks = jaxfoam.load_trajectory(tmp_path / "blocks.h5")
    for n in parts["frames"]:
        np.testing.assert_array_equal(blocks.frames[n], whole.frames[n])
    assert json.loads(whole.scene_json) == scene.spec


def test_interrupted_run_is_marked_incomplete(tmp_path):
    parts = _parts(np.float64)
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(tmp_path / "p.h5", parts["params"], parts["scene"], 0.01, 1e-4, 10) as w:
            w.append({n: a[:1] for n, a in parts["frames"].items()}, [0.0])
            raise RuntimeError("simulated crash")
    back = jaxfoam.load_trajectory(tmp_path / "p.h5")
    assert not back.complete and back.num_frames == 1


def test_writer_rejects_bad_input(tmp_path):
    parts = _parts(np.float64)
    with TrajectoryWriter(tmp_path / "w.h5", parts["params"], parts["scene"], 0.01, 1e-4, 10) as w:
        with pytest.raises(ValueError, match="strictly increasing"):
            w.append({n: a[:2] for n, a in parts["frames"].items()}, [0.2, 0.1])
        with pytest.raises(ValueError, match=r"frames\['x'\] must have shape"):
            w.append({"x": parts["frames"]["x"][:2]}, [0.0])
    with pytest.raises(ValueError, match="dx must be a positive"):
        TrajectoryWriter(tmp_path / "w2.h5", parts["params"], parts["scene"], 0.0, 1e-4, 10)
    with pytest.raises(ValueError, match="parts .* missing"):
        jaxfoam.save_trajectory(tmp_path / "w3.h5", {"frames": parts["frames"]})


def _corrupt(path, edit):
    with h5py.File(path, "a") as f:
        edit(f)
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda f: f.attrs.__setitem__("format", "jaxfoam-silhouettes"), "not a jaxfoam trajectory"),
    (lambda f: f.attrs.__delitem__("format"), "not a jaxfoam trajectory"),
    (lambda f: f.attrs.__setitem__("format_version", 99), "unsupported format_version 99"),
    (lambda f: f.__delitem__("frames/x"), "missing '/frames/x'"),
    (lambda f: f["times"].resize((2,)), r"'/frames/\w+' has shape"),
    (lambda f: f["params"].attrs.__delitem__("sigma_y"), r"lacks attributes \['sigma_y'\]"),
    (lambda f: f["scene"].attrs.__setitem__("json", "{not json"), "json does not parse"),
    (lambda f: f.attrs.__delitem__("dx"), "missing root attribute 'dx'"),
])
def test_bad_trajectory_files_are_rejected(tmp_path, edit, message):
    path = _corrupt(jaxfoam.save_trajectory(tmp_path / "t.h5", _parts(np.float64)), edit)
    with pytest.raises(jaxfoam.TrajectoryError, match=message):
        jaxfoam.load_trajectory(path)


def test_non_trajectory_files_are_rejected(tmp_path):
    with pytest.raises(FileNotFoundError):
        jaxfoam.load_trajectory(tmp_path / "missing.h5")
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    with pytest.raises(jaxfoam.TrajectoryError, match="not an HDF5 file"):
        jaxfoam.load_trajectory(text)
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["masks"] = np.zeros((2, 4, 4), np.uint8)
    with pytest.raises(jaxfoam.TrajectoryError, match="not a jaxfoam trajectory"):
        jaxfoam.load_trajectory(tmp_path / "other.h5")


@pytest.mark.slow
def test_cli_simulate_then_render_end_to_end(tmp_path, capsys):
    out = tmp_path / "run.h5"
    code = cli.main(["simulate", str(CLI_SCENE), "--out", str(out), "--dx", str(TINY_DX[2]), "--dtype", CLI_DTYPE,
                     "--frames", str(TINY["frames"]), "--duration", str(TINY["duration"])])
    assert code == 0
    captured = capsys.readouterr()
    assert "substeps/s" in captured.err and "t = 0.004/0.004 s" in captured.err  # the progress bar
    traj = jaxfoam.load_trajectory(out)
    assert traj.num_frames == TINY["frames"] + 1 and traj.complete and traj.dtype == "float32"
    np.testing.assert_allclose(traj.times, [0.0, 0.002, 0.004], rtol=1e-12)
    assert traj.params == jaxfoam.Params(mu=cli.DEFAULT_MU, kappa=3000.0, sigma_y=cli.DEFAULT_SIGMA_Y,
                                         eta=cli.DEFAULT_ETA, m=cli.DEFAULT_M, rho=80.0)
    assert np.isfinite(traj.frames["x"]).all() and traj.frames["x"].dtype == np.float32
    # The module entry point renders it in a fresh process (no simulation, no compilation).
    png = tmp_path / "run.png"
    res = subprocess.run([sys.executable, "-m", "jaxfoam", "render", str(out), "--out", str(png), "--panels", "3"],
                         capture_output=True, text=True, timeout=120, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert res.returncode == 0, res.stderr
    assert png.stat().st_size > 10_000
    import matplotlib.image as mpimg

    img = mpimg.imread(png)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400
    assert img[..., :3].std() > 0.05  # not a blank page


def test_cli_reports_bad_input_with_exit_code_2(tmp_path, capsys):
    scene = json.loads(CLI_SCENE.read_text())
    scene["colour"] = "red"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(scene))
    assert cli.main(["simulate", str(bad), "--out", str(tmp_path / "x.h5")]) == 2
    assert "unknown key(s) ['colour']" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # an option's range is checked as it is parsed
        cli.main(["simulate", str(CLI_SCENE), "--out", str(tmp_path / "x.h5"), "--sigma-y", "-1"])
    assert info.value.code == 2
    assert "argument --sigma-y: must be a finite number >= 0 Pa, got '-1'" in capsys.readouterr().err
    (tmp_path / "junk.h5").write_text("junk")
    assert cli.main(["render", str(tmp_path / "junk.h5"), "--out", str(tmp_path / "x.png")]) == 2
    assert "not an HDF5 file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["simulate", str(CLI_SCENE), "--out", "x.h5", "--dtype", "float16"])


def test_progress_bar_reports_time_and_speed():
    stream = io.StringIO()
    bar = cli.Progress(t_end=1.0, total_frames=4, particles=1000, stream=stream)
    bar.update(0.0, 0, 0, force=True)
    bar.update(0.25, 1, 100, force=True)
    bar.update(0.5, 2, 200, force=True)
    lines = stream.getvalue().splitlines()
    assert "compiling" in lines[0] and "t = 0.500/1.000 s" in lines[2] and "frame 2/4" in lines[2]
    assert "substeps/s" in lines[2] and "M particle-steps/s" in lines[2]


def test_plates_drawn_at_their_position_at_frame_time():
    from jaxfoam.render import _Style

    parts = _parts(np.float64, scene="hanging_plate_2d.json")
    traj = jaxfoam._trajectory.as_saved_trajectory(parts)
    style = _Style(traj, "gamma_dot", np.arange(3))
    plate = json.loads(parts["scene"])["plate"]
    # sin(2 pi 3 Hz 0.75 s) = 1 and the 0.3 s ramp is over: the plate is displaced by the full amplitude.
    (corner, size), = style.plate_rects(0.75)
    cx = plate["center"][0] + plate["motion"]["amplitude"]
    np.testing.assert_allclose(corner, [cx - plate["half_size"][0], plate["center"][1] - plate["half_size"][1]],
                               atol=1e-12)
    np.testing.assert_allclose(size, 2 * np.asarray(plate["half_size"]), atol=1e-12)
    (corner0, _), = style.plate_rects(0.0)
    np.testing.assert_allclose(corner0[0], plate["center"][0] - plate["half_size"][0], atol=1e-12)


def test_3d_render_projects_with_nearest_particles_on_top(tmp_path):
    from jaxfoam.render import _Style, render_contact_sheet

    parts = _parts(np.float64, dim=3, scene="squeeze_3d.json")
    traj = jaxfoam._trajectory.as_saved_trajectory(parts)
    style = _Style(traj, "s", np.arange(3))
    xy, c = style.values(1)
    x, a = parts["frames"]["x"][1], parts["frames"]["active"][1]
    order = np.argsort(x[a][:, 2], kind="stable")  # far (small z) first: the camera looks along -z
    np.testing.assert_array_equal(xy, x[a][order][:, :2])
    np.testing.assert_array_equal(c, parts["frames"]["s"][1][a][order])
    png = render_contact_sheet(traj, tmp_path / "s3d.png", n_frames=3, color="s")
    assert Path(png).stat().st_size > 10_000
    with pytest.raises(ValueError, match="color must be one of"):
        render_contact_sheet(traj, tmp_path / "bad.png", color="speed")
    del traj.frames["gamma_dot"]
    with pytest.raises(ValueError, match="no per-particle field 'gamma_dot'"):
        render_contact_sheet(traj, tmp_path / "bad.png")


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # the ffmpeg reader's subprocess
def test_video_has_one_frame_per_trajectory_frame(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    from jaxfoam.render import render_video

    traj = jaxfoam._trajectory.as_saved_trajectory(_parts(np.float32, scene="hanging_plate_2d.json"))
    out = render_video(traj, tmp_path / "v.mp4", fps=10, width_px=320)
    with imageio.get_reader(out) as r:
        frames = [f for f in r]
    assert len(frames) == traj.num_frames
    h, w = frames[0].shape[:2]
    assert w == 320 and h % 16 == 0


# The scene test compiles one substep per scene without LLVM optimization: it checks that the scene
# runs, not how fast, and the default optimization level doubles the compile time (measured 10 s -> 4 s
# for a 3D scene on one core).
FAST_COMPILE = {"xla_backend_optimization_level": 0}
SCENE_SUBSTEPS = 3


@pytest.mark.slow
@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_example_scene_loads_and_runs(path):
    import jax

    spec = json.loads(path.read_text())
    scene = jaxfoam.load_scene(path)
    dx = TINY_DX[scene.dim]
    params = jaxfoam.Params(mu=cli.DEFAULT_MU, kappa=scene.kappa, sigma_y=cli.DEFAULT_SIGMA_Y, eta=cli.DEFAULT_ETA,
                            m=cli.DEFAULT_M, rho=scene.density)
    model = jaxfoam.make_model(scene, dx, params_ref=params)
    state = model.sample()
    step = jax.jit(jaxfoam.step).lower(model, state, params).compile(compiler_options=FAST_COMPILE)
    x0 = np.asarray(state.x)
    for _ in range(SCENE_SUBSTEPS):
        state = step(model, state, params)
    x, v, active = np.asarray(state.x), np.asarray(state.v), np.asarray(state.active)
    assert active.sum() > 20
    for name in ("x", "v", "F", "bbar_e"):
        assert np.isfinite(np.asarray(getattr(state, name))[active]).all(), name
    assert (np.asarray(jaxfoam.det(state.F))[active] > 0).all()
    assert np.abs(x - x0).max() < 3 * dx  # a few substeps move particles by far less than a cell
    if scene.kind == "drop":
        # Nothing touches the blob yet: momentum balance gives a centre-of-mass velocity v0 + g t
        # (equal particle masses, so the mean velocity).
        t = SCENE_SUBSTEPS * model.dt
        np.testing.assert_allclose(v[active].mean(axis=0),
                                   np.asarray(spec["initial_velocity"]) + np.asarray(scene.gravity) * t,
                                   rtol=0, atol=1e-9)
    if scene.kind == "hanging_plate":
        # The foam's top lies inside the sticky plate (that is what holds it up).
        plate = spec["plate"]
        assert x0[active][:, 1].max() > plate["center"][1] - plate["half_size"][1]
    if scene.kind == "squeeze":
        # The plate first moves down (squeeze), then up (pull), and starts above the foam.
        plate = spec["plates"][0]
        ys = np.asarray(plate["motion"]["positions"])[:, 1]
        assert ys.argmin() not in (0, len(ys) - 1) and ys[-1] > ys[0]
        assert x0[active][:, 1].max() <= plate["center"][1] - plate["half_size"][1]
