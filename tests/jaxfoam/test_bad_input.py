"""Bad input, across the command line (simulate, render, synth, track, fit) and the Python API.

Each command-line case asserts exit status 2, no traceback, the `jaxfoam <command>: error:` line and the
words that name the option or field (and its value or range); each API case asserts a ValueError
subclass whose message names the field. Every case is refused before any simulation, so the suite
compiles nothing.
"""
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

import jaxfoam
from jaxfoam import cli
from fitting import read_silhouettes, write_silhouettes
from fitting.io import camera_covering

from helpers import edited

ROOT = Path(__file__).resolve().parents[2]
HANGING = ROOT / "experiments" / "scenes" / "hanging_plate_2d.json"
DROP = ROOT / "experiments" / "scenes" / "drop_2d.json"
HANGING_SPEC = json.loads(HANGING.read_text())
DROP_SPEC = json.loads(DROP.read_text())


_edit = edited


BAD_SCENES = {
    # name: (scene dict, words of the message)
    "dim float": (_edit(HANGING_SPEC, ["dim"], 2.0), ["'dim'", "integer 2 or 3", "2.0"]),
    "dim float without gravity": (_edit(_edit(HANGING_SPEC, ["dim"], 2.0), ["gravity"], delete=True),
                                  ["'dim'", "integer 2 or 3", "2.0"]),
    "hanging plate outside the domain": (_edit(HANGING_SPEC, ["plate", "center"], [0.0, 5.0]),
                                         ["'plate'", "outside the domain", "center"]),
    "extra plate of a drop outside": (_edit(DROP_SPEC, ["plates"], [{"center": [3.0, 0.1], "half_size": [0.05, 0.01]}]),
                                      ["'plates[0]'", "outside the domain"]),
    "box entirely outside the domain": (_edit(HANGING_SPEC, ["initial_shape", "max"], [0.3, 0.3037]) | {
        "initial_shape": {"type": "box", "min": [0.2, 0.22], "max": [0.3, 0.3]}},
        ["'initial_shape'", "x in [0.2, 0.3]", "entirely outside the domain's [-0.15, 0.15]"]),
    "ellipse entirely outside the domain": (_edit(DROP_SPEC, ["initial_shape", "center"], [-0.04, 0.5]),
                                            ["'initial_shape'", "entirely outside the domain"]),
    "material inside the floor": (_edit(_edit(DROP_SPEC, ["floor", "y"], 0.13), ["plates"], []),
                                  ["'initial_shape'", "below the floor", "floor.y = 0.13"]),
    "floor above the domain": (_edit(DROP_SPEC, ["floor", "y"], 0.5), ["'floor.y'", "[0, 0.25)", "0.5"]),
}


# ------------------------------------------------------------------------------------------------
# Files the cases start from (nothing here simulates)
# ------------------------------------------------------------------------------------------------

def _trajectory_parts(n=40, frames=3):
    rng = np.random.default_rng(0)
    x = np.stack([np.column_stack([rng.uniform(-0.04, 0.04, n), rng.uniform(0.12, 0.18, n) - 0.01 * k])
                  for k in range(frames)])
    return dict(frames=dict(x=x, v=np.zeros_like(x), gamma_dot=np.zeros(x.shape[:2]), s=np.zeros(x.shape[:2]),
                            J=np.ones(x.shape[:2]), active=np.ones(x.shape[:2], bool)),
                times=np.arange(frames) * 0.01, params=jaxfoam.Params(mu=200.0, kappa=3000.0, sigma_y=40.0, eta=10.0,
                                                                        m=0.5, rho=80.0),
                scene=DROP_SPEC, dx=0.005, dt=1e-4, substeps=100, ppc=4)


def _ellipse_masks(spec, times, pixel_size=0.005):
    scene = jaxfoam.load_scene(spec)
    camera, (H, W) = camera_covering(scene, pixel_size)
    x, y = camera.pixel_centers((H, W))
    c, r = np.asarray(spec["initial_shape"]["center"]), np.asarray(spec["initial_shape"]["radii"])
    inside = ((x[None, :] - c[0]) / r[0]) ** 2 + ((y[:, None] - c[1]) / r[1]) ** 2 <= 1.0
    return np.repeat(inside[None].astype(np.uint8), len(times), axis=0), camera


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_input")
    f = {"dir": d, "scene": d / "scene.json", "drop": d / "drop.json"}
    f["scene"].write_text(json.dumps(HANGING_SPEC))
    f["drop"].write_text(json.dumps(DROP_SPEC))
    for name, (spec, _) in BAD_SCENES.items():
        f[name] = d / (name.replace(" ", "_") + ".json")
        f[name].write_text(json.dumps(spec))
    f["kappa_slip"] = d / "kappa_slip.json"
    f["kappa_slip"].write_text(json.dumps(dict(HANGING_SPEC, kappa=1e12)))
    f["latin1"] = d / "latin1.json"
    f["latin1"].write_bytes(json.dumps(dict(HANGING_SPEC, notes="caf\u00e9"), ensure_ascii=False).encode("latin-1"))
    f["not_json"] = d / "notes.json"
    f["not_json"].write_text("kind: drop\n")
    f["array"] = d / "array.json"
    f["array"].write_text("[1, 2]")
    f["first_mask"] = d / "first_mask.json"
    f["first_mask"].write_text(json.dumps(dict(DROP_SPEC, initial_shape={"type": "first_mask"})))
    f["outdir"] = d / "outdir"
    f["outdir"].mkdir()
    f["text"] = d / "notes.h5"
    f["text"].write_text("these are notes, not HDF5\n")
    f["traj"] = Path(jaxfoam.save_trajectory(d / "traj.h5", _trajectory_parts()))
    parts = _trajectory_parts()
    parts["frames"]["x"][2, 5, 0] = np.nan
    f["traj_png"] = d / "traj.png"  # a trajectory file under a picture's name
    shutil.copy(f["traj"], f["traj_png"])
    f["traj_nan"] = Path(jaxfoam.save_trajectory(d / "traj_nan.h5", parts))
    f["traj_cut"] = d / "traj_cut.h5"
    blob = f["traj"].read_bytes()
    f["traj_cut"].write_bytes(blob[:int(0.6 * len(blob))])
    # Silhouettes of the drop's ellipse (not simulated): the good file and its faulty variants.
    times = np.array([0.0, 0.05, 0.1, 0.15])
    masks, camera = _ellipse_masks(DROP_SPEC, times)
    f["data"] = d / "data.h5"
    write_silhouettes(f["data"], masks, times, camera, DROP_SPEC)
    write_silhouettes(d / "data_ms.h5", masks, times * 1000.0 * 13.33, camera, DROP_SPEC)
    f["data_ms"] = d / "data_ms.h5"
    f["data_empty"] = d / "data_empty.h5"
    write_silhouettes(f["data_empty"], np.zeros_like(masks), times, camera, DROP_SPEC)
    f["data_full"] = d / "data_full.h5"
    write_silhouettes(f["data_full"], np.ones_like(masks), times, camera, DROP_SPEC)
    f["data_pixel10"] = d / "data_pixel10.h5"
    big = dict(model="orthographic", pixel_size=10.0, origin=[-125.0, -125.0], axis="z")
    write_silhouettes(f["data_pixel10"], masks[:, :25, :25], times, big, DROP_SPEC)
    f["data_corrupt"] = d / "data_corrupt.h5"
    shutil.copy(f["data"], f["data_corrupt"])
    with h5py.File(f["data_corrupt"], "r") as h:
        info = h["masks"].id.get_chunk_info(0)
    with open(f["data_corrupt"], "r+b") as fh:
        fh.seek(info.byte_offset)
        fh.write(b"\xff" * info.size)
    f["null_fit"] = d / "null_fit.json"
    f["null_fit"].write_text(json.dumps({"params": {"sigma_y": float("nan"), "mu": 100.0}}))
    f["latin1_fit"] = d / "latin1_fit.json"
    f["latin1_fit"].write_bytes('{"params": {"sigma_y": 30.0}, "note": "caf\u00e9"}'.encode("latin-1"))
    f["video_empty"] = d / "empty.mp4"
    f["video_empty"].write_bytes(b"")
    f["video_text"] = d / "text.mp4"
    f["video_text"].write_text("not a video\n")
    f["frames_dir"] = d / "frames"
    f["frames_dir"].mkdir()
    import imageio.v3 as iio

    f["bad_frames"] = d / "bad_frames"
    f["bad_frames"].mkdir()
    for k in range(2):
        iio.imwrite(f["frames_dir"] / f"f{k}.png", np.zeros((16, 16, 3), np.uint8))
    iio.imwrite(f["bad_frames"] / "f0.png", np.zeros((16, 16, 3), np.uint8))
    (f["bad_frames"] / "f1.png").write_text("not a picture\n")
    return f


# ------------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------------

OUT = "{dir}/out.h5"
SIM = ["simulate", "{scene}", "--out", OUT, "--quiet"]
RENDER = ["render", "{traj}", "--out", "{dir}/out.png"]
SYNTH = ["synth", "{drop}", "--params", "mu=200,sigma_y=40,eta=10,m=0.5", "--out", OUT]
TRACK = ["track", "{frames_dir}", "--fps", "10", "--scene", "{drop}", "--pixel-size", "0.005", "--origin", "-0.15", "0",
         "--out", OUT]
FIT = ["fit", "{data}", "--out", "{dir}/fit.json", "--no-plots"]

CLI_CASES = {
    # name: (argv, words the error must contain)
    "simulate --dx 0": (SIM + ["--dx", "0"], ["--dx", "> 0", "'0'"]),
    "simulate --dx -1": (SIM + ["--dx", "-1"], ["--dx", "> 0", "'-1'"]),
    "simulate --dx nan": (SIM + ["--dx", "nan"], ["--dx", "finite", "'nan'"]),
    "simulate --dx text": (SIM + ["--dx", "fine"], ["--dx", "'fine'"]),
    "simulate --ppc 0": (SIM + ["--ppc", "0"], ["--ppc", ">= 1", "'0'"]),
    "simulate --ppc 1.5": (SIM + ["--ppc", "1.5"], ["--ppc", "integer", "'1.5'"]),
    "simulate --frames 0": (SIM + ["--frames", "0"], ["--frames", ">= 1", "'0'"]),
    "simulate --frames text": (SIM + ["--frames", "ten"], ["--frames", "'ten'"]),
    "simulate --duration 0": (SIM + ["--duration", "0"], ["--duration", "> 0", "'0'"]),
    "simulate --duration inf": (SIM + ["--duration", "inf"], ["--duration", "finite", "'inf'"]),
    "simulate --mu 0": (SIM + ["--mu", "0"], ["--mu", "> 0 Pa", "'0'"]),
    "simulate --mu -1": (SIM + ["--mu", "-1"], ["--mu", "> 0 Pa", "'-1'"]),
    "simulate --sigma-y -1": (SIM + ["--sigma-y", "-1"], ["--sigma-y", ">= 0 Pa", "'-1'"]),
    "simulate --eta -1": (SIM + ["--eta", "-1"], ["--eta", ">= 0 Pa s^m", "'-1'"]),
    "simulate --m 0": (SIM + ["--m", "0"], ["--m", "(0, 5]", "'0'"]),
    "simulate --m 6": (SIM + ["--m", "6"], ["--m", "(0, 5]", "'6'"]),
    "simulate --seed -1": (SIM + ["--seed", "-1"], ["--seed", ">= 0", "'-1'"]),
    "simulate --cfl 0": (SIM + ["--cfl", "0"], ["--cfl", "(0, 1]", "'0'"]),
    "simulate --cfl 2": (SIM + ["--cfl", "2"], ["--cfl", "(0, 1]", "'2'"]),
    "simulate --max-particles 0": (SIM + ["--max-particles", "0"], ["--max-particles", ">= 1"]),
    "simulate --max-substeps 0": (SIM + ["--max-substeps", "0"], ["--max-substeps", ">= 1"]),
    "simulate --dtype float16": (SIM + ["--dtype", "float16"], ["--dtype", "float16", "float32"]),
    "simulate --dx 1e-4 over the particle budget": (SIM + ["--dx", "1e-4"],
                                                    ["--dx 0.0001", "particles", "MiB",
                                                     "--max-particles"]),
    "simulate --ppc 1000000 over the particle budget": (SIM + ["--ppc", "1000000"],
                                                        ["--ppc 1000000", "particles", "--max-particles"]),
    "simulate --mu 1e30 over the substep budget": (SIM + ["--mu", "1e30"], ["substeps", "--max-substeps", "mu"]),
    "simulate kappa 1e12 over the substep budget": (["simulate", "{kappa_slip}", "--out", OUT],
                                                    ["substeps", "--max-substeps", "kappa"]),
    "simulate float32 --mu 1e39": (SIM + ["--dtype", "float32", "--mu", "1e39"], ["--mu", "1e+39", "float32"]),
    "simulate --out a directory": (["simulate", "{scene}", "--out", "{outdir}"], ["--out", "is a directory"]),
    "simulate --out the scene": (["simulate", "{scene}", "--out", "{scene}"], ["--out", "same file as the scene"]),
    "simulate --out empty": (["simulate", "{scene}", "--out", ""], ["--out", "empty"]),
    "simulate missing scene": (["simulate", "{dir}/missing.json", "--out", OUT], ["missing.json", "cannot read file"]),
    "simulate scene not UTF-8": (["simulate", "{latin1}", "--out", OUT], ["latin1.json", "UTF-8"]),
    "simulate scene not JSON": (["simulate", "{not_json}", "--out", OUT], ["notes.json", "not valid JSON"]),
    "simulate scene a JSON array": (["simulate", "{array}", "--out", OUT], ["'scene'", "expected an object"]),
    "simulate scene a directory": (["simulate", "{outdir}", "--out", OUT], ["outdir", "cannot read file"]),
    **{f"simulate {name}": (["simulate", "{" + name + "}", "--out", OUT], words)
       for name, (_, words) in BAD_SCENES.items()},

    "render missing trajectory": (["render", "{dir}/missing.h5", "--out", "{dir}/o.png"], ["missing.h5", "does not exist"]),
    "render a text file": (["render", "{text}", "--out", "{dir}/o.png"], ["notes.h5", "not an HDF5 file"]),
    "render a silhouette file": (["render", "{data}", "--out", "{dir}/o.png"], ["data.h5", "not a jaxfoam trajectory"]),
    "render a truncated trajectory": (["render", "{traj_cut}", "--out", "{dir}/o.png"], ["traj_cut.h5"]),
    "render non-finite positions": (["render", "{traj_nan}", "--out", "{dir}/o.png"],
                                    ["traj_nan.h5", "'/frames/x'", "non-finite", "frame 2"]),
    "render --panels 0": (RENDER + ["--panels", "0"], ["--panels", ">= 1", "'0'"]),
    "render --fps 0": (RENDER + ["--fps", "0", "--mp4", "{dir}/o.mp4"], ["--fps", "> 0", "'0'"]),
    "render --color": (RENDER + ["--color", "speed"], ["--color", "speed", "gamma_dot"]),
    "render --out the trajectory": (["render", "{traj}", "--out", "{traj}"], ["--out", "same file as the trajectory"]),
    "render --out a .h5 file": (["render", "{traj}", "--out", "{dir}/sheet.h5"], ["--out", "sheet.h5", ".png", "'.h5'"]),
    "render --out a picture named like the trajectory": (["render", "{traj_png}", "--out", "{traj_png}"],
                                                         ["--out", "same file as the trajectory"]),
    "render --mp4 a GIF": (RENDER + ["--mp4", "{dir}/o.gif"], ["--mp4", "o.gif", ".mp4", "'.gif'"]),
    "track a corrupt image in the directory": (["track", "{bad_frames}"] + TRACK[2:], ["f1.png", "cannot read image"]),
    "render --out a directory": (["render", "{traj}", "--out", "{outdir}"], ["--out", "is a directory"]),
    "render --mp4 the trajectory": (RENDER + ["--mp4", "{traj}"], ["--mp4", "same file as the trajectory"]),

    "synth --params missing m": (["synth", "{drop}", "--params", "mu=200,sigma_y=40,eta=10", "--out", OUT],
                                 ["--params", "missing", "'m'"]),
    "synth --params not a number": (["synth", "{drop}", "--params", "mu=soft,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                                    ["--params", "mu", "'soft'"]),
    "synth --params kappa": (["synth", "{drop}", "--params", "kappa=1,mu=2,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                             ["--params", "kappa", "scene"]),
    "synth --params unknown": (["synth", "{drop}", "--params", "nu=1,mu=2,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                               ["--params", "'nu'"]),
    "synth --params mu -1": (["synth", "{drop}", "--params", "mu=-1,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                             ["Params.mu", "> 0 Pa", "-1"]),
    "synth --params mu 1e30 over the substep budget": (
        ["synth", "{drop}", "--params", "mu=1e30,sigma_y=40,eta=10,m=0.5", "--out", OUT], ["substeps", "--max-substeps"]),
    "synth --frames 1": (SYNTH + ["--frames", "1"], ["--frames", ">= 2", "'1'"]),
    "synth --noise 2": (SYNTH + ["--noise", "2"], ["--noise", "[0, 1]", "'2'"]),
    "synth --drop-frames 1": (SYNTH + ["--drop-frames", "1"], ["--drop-frames", "[0, 1)", "'1'"]),
    "synth --pixel-size 0": (SYNTH + ["--pixel-size", "0"], ["--pixel-size", "> 0", "'0'"]),
    "synth --pixel-size in um": (SYNTH + ["--pixel-size", "1e-6"], ["pixel_size", "1e-06", "pixels", "not mm or um"]),
    "synth --dx 1e-4 over the particle budget": (SYNTH + ["--dx", "1e-4"], ["--dx 0.0001", "--max-particles"]),
    "synth --seed -1": (SYNTH + ["--seed", "-1"], ["--seed", ">= 0", "'-1'"]),
    "synth --cfl 0": (SYNTH + ["--cfl", "0"], ["--cfl", "(0, 1]", "'0'"]),
    "synth --out the scene": (["synth", "{drop}", "--params", "mu=200,sigma_y=40,eta=10,m=0.5", "--out", "{drop}"],
                              ["--out", "same file as the scene"]),
    "synth first_mask scene": (["synth", "{first_mask}", "--params", "mu=200,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                               ["initial_shape", "first_mask"]),
    "synth missing scene": (["synth", "{dir}/missing.json", "--params", "mu=200,sigma_y=40,eta=10,m=0.5", "--out", OUT],
                            ["missing.json", "cannot read file"]),

    "track missing video": (["track", "{dir}/missing.mp4"] + TRACK[2:], ["missing.mp4", "does not exist"]),
    "track zero-byte video": (["track", "{video_empty}"] + TRACK[2:], ["empty.mp4", "empty"]),
    "track text video": (["track", "{video_text}"] + TRACK[2:], ["text.mp4", "cannot read"]),
    "track --pixel-size 0": (TRACK + ["--pixel-size", "0"], ["--pixel-size", "> 0", "'0'"]),
    "track --pixel-size -1": (TRACK + ["--pixel-size", "-1"], ["--pixel-size", "> 0", "'-1'"]),
    "track --origin nan": (TRACK + ["--origin", "nan", "0"], ["--origin", "finite", "'nan'"]),
    "track --threshold 1.5": (TRACK + ["--threshold", "1.5"], ["--threshold", "(0, 1)", "'1.5'"]),
    "track --fps 0": (TRACK + ["--fps", "0"], ["--fps", "> 0", "'0'"]),
    "track --every 0": (TRACK + ["--every", "0"], ["--every", ">= 1", "'0'"]),
    "track --downsample 0": (TRACK + ["--downsample", "0"], ["--downsample", ">= 1", "'0'"]),
    "track --max-frames 0": (TRACK + ["--max-frames", "0"], ["--max-frames", ">= 1", "'0'"]),
    "track --open -1": (TRACK + ["--open", "-1"], ["--open", ">= 0", "'-1'"]),
    "track --plate-margin -2": (TRACK + ["--plate-margin", "-2"], ["--plate-margin", ">= -1", "'-2'"]),
    "track --t0 -1": (TRACK + ["--t0", "-1"], ["--t0", ">= 0", "'-1'"]),
    "track --out the video directory": (TRACK[:-1] + ["{frames_dir}"], ["--out", "is a directory"]),
    "track --out the scene": (TRACK[:-1] + ["{drop}"], ["--out", "same file as --scene"]),
    "track bad scene": (["track", "{frames_dir}", "--fps", "10", "--scene", "{dim float}", "--pixel-size", "0.005",
                         "--origin", "0", "0", "--out", OUT], ["'dim'", "integer 2 or 3"]),
    "track image directory without --fps": (TRACK[:2] + TRACK[4:], ["fps", "--fps"]),
    "track --background missing image": (TRACK + ["--background", "{dir}/empty_scene.png"],
                                         ["--background", "empty_scene.png"]),

    "fit missing data": (["fit", "{dir}/missing.h5", "--out", "{dir}/fit.json"], ["missing.h5"]),
    "fit a text file": (["fit", "{text}", "--out", "{dir}/fit.json"], ["notes.h5", "cannot open as HDF5"]),
    "fit a trajectory file": (["fit", "{traj}", "--out", "{dir}/fit.json"], ["traj.h5", "'format'"]),
    "fit --out the data": (["fit", "{data}", "--out", "{data}"], ["--out", "same file as the data"]),
    "fit --log the data": (FIT + ["--log", "{data}"], ["--log", "same file as the data"]),
    "fit --log the result": (FIT + ["--log", "{dir}/fit.json"], ["--log", "same file as --out"]),
    "fit --out a directory": (["fit", "{data}", "--out", "{outdir}"], ["--out", "is a directory"]),
    "fit --dx 0": (FIT + ["--dx", "0"], ["--dx", "> 0", "'0'"]),
    "fit --ppc 0": (FIT + ["--ppc", "0"], ["--ppc", ">= 1", "'0'"]),
    "fit --starts 0": (FIT + ["--starts", "0"], ["--starts", ">= 1", "'0'"]),
    "fit --max-iter -1": (FIT + ["--max-iter", "-1"], ["--max-iter", ">= 0", "'-1'"]),
    "fit --seed -1": (FIT + ["--seed", "-1"], ["--seed", ">= 0", "'-1'"]),
    "fit --pixel-level -1": (FIT + ["--pixel-level", "-1"], ["--pixel-level", ">= 0", "'-1'"]),
    "fit --pixel-level 60": (FIT + ["--pixel-level", "60"], ["pixel_level", "[0, 2]", "50x60", "60"]),
    "fit --optimizer": (FIT + ["--optimizer", "newton"], ["--optimizer", "newton", "lm"]),
    "fit --fix not a number": (FIT + ["--fix", "mu=stiff"], ["--fix", "mu", "'stiff'"]),
    "fit --fix unknown": (FIT + ["--fix", "nu=1"], ["'nu'"]),
    "fit --bounds reversed": (FIT + ["--bounds", "mu=500:5"], ["mu", "lo < hi", "500"]),
    "fit --time-window reversed": (FIT + ["--time-window", "1:0"], ["time_window", "t_lo < t_hi"]),
    "fit --time-budget negative": (FIT + ["--time-budget", "-5"], ["--time-budget", "-5"]),
    "fit --dx 1e-4 over the particle budget": (FIT + ["--dx", "1e-4"], ["--dx 0.0001", "--max-particles"]),
    "fit times in milliseconds": (["fit", "{data_ms}", "--out", "{dir}/fit.json", "--no-plots"],
                                  ["substeps", "--max-substeps", "milliseconds"]),
    "fit masks without foam": (["fit", "{data_empty}", "--out", "{dir}/fit.json"], ["masks", "no foam pixel"]),
    "fit masks all foam": (["fit", "{data_full}", "--out", "{dir}/fit.json"], ["masks", "every pixel", "no boundary"]),
    "fit pixel size of 10 m": (["fit", "{data_pixel10}", "--out", "{dir}/fit.json"],
                               ["camera.pixel_size = 10 m", "pixels", "not mm or um"]),
    "fit corrupted masks chunk": (["fit", "{data_corrupt}", "--out", "{dir}/fit.json"],
                                  ["data_corrupt.h5", "'masks'", "damaged"]),
    "fit --start a result with NaN parameters": (FIT + ["--start", "{null_fit}"],
                                                  ["--start", "null_fit.json", "non-finite"]),
    "fit --start a non-UTF-8 result": (FIT + ["--start", "{latin1_fit}"], ["--start", "latin1_fit.json", "not a fit result"]),
    "fit --resume a text log": (FIT + ["--resume", "--log", "{text}"], ["notes.h5", "fit log", "--resume"]),
    "fit --resume a truncated log": (FIT + ["--resume", "--log", "{traj_cut}"], ["traj_cut.h5", "fit log"]),
}


def _fill(argv, files):
    return [a.format(**{k: str(v) for k, v in files.items()}) for a in argv]


@pytest.mark.parametrize("name", sorted(CLI_CASES))
def test_cli_bad_input(name, files, capsys):
    argv, words = CLI_CASES[name]
    argv = _fill(argv, files)
    before = {p: p.stat().st_mtime_ns for p in files["dir"].rglob("*") if p.is_file()}
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse refuses a value as it parses it
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, f"{name}: exit {code}\n{err}"
    assert "Traceback" not in err
    assert f"jaxfoam {argv[0]}: error:" in err, err
    missing = [w for w in words if w not in err]
    assert not missing, f"{name}: {err!r} lacks {missing}"
    # A refused command leaves every input as it was and writes nothing.
    after = {p: p.stat().st_mtime_ns for p in files["dir"].rglob("*") if p.is_file()}
    assert after == before, f"{name}: files changed: {set(after.items()) ^ set(before.items())}"


def test_scene_named_like_json_text_is_read_as_a_file(files, tmp_path):
    """A valid scene in a file named `{run1}.json` is a file, not JSON text."""
    path = tmp_path / "{run1}.json"
    shutil.copy(files["scene"], path)
    assert jaxfoam.load_scene(str(path)).kind == "hanging_plate"
    assert jaxfoam.load_scene(path).kind == "hanging_plate"


def test_track_without_the_viz_extra_names_it(files, capsys, monkeypatch):
    import jaxfoam.guards as guards

    monkeypatch.setattr(guards, "missing_modules", lambda *mods: list(mods))
    assert cli.main(_fill(TRACK, files)) == 2
    err = capsys.readouterr().err
    assert "jaxfoam track: error:" in err and "imageio" in err and "pip install 'jaxfoam[viz]'" in err


def test_render_without_the_viz_extra_names_it(files, capsys, monkeypatch):
    import jaxfoam.guards as guards

    monkeypatch.setattr(guards, "missing_modules", lambda *mods: list(mods))
    assert cli.main(_fill(RENDER, files)) == 2
    err = capsys.readouterr().err
    assert "jaxfoam render: error:" in err and "matplotlib" in err and "jaxfoam[viz]" in err


# ------------------------------------------------------------------------------------------------
# Python API
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(BAD_SCENES))
def test_api_bad_scene(name):
    spec, words = BAD_SCENES[name]
    for form in (spec, json.dumps(spec)):
        with pytest.raises(jaxfoam.SceneError) as info:
            jaxfoam.load_scene(form)
        assert all(w in str(info.value) for w in words), str(info.value)


def test_api_plate_that_never_touches_the_material_warns():
    spec = _edit(HANGING_SPEC, ["plate", "center"], [0.0, 0.06])
    spec["plate"]["motion"] = {"type": "none"}
    with pytest.warns(jaxfoam._scene.PlausibilityWarning, match="'plate': the plate never touches"):
        jaxfoam.load_scene(spec)


def test_api_shape_half_outside_the_domain_warns_that_it_is_clipped():
    spec = _edit(HANGING_SPEC, ["initial_shape", "max"], [0.3, 0.3037])
    with pytest.warns(jaxfoam._scene.PlausibilityWarning, match=r"x in \[-0.05, 0.3\] m, beyond the domain's"):
        jaxfoam.load_scene(spec)


def test_api_stiff_material_warns_per_frame_and_is_refused_over_the_budget():
    from jaxfoam.guards import BudgetError, check_substeps

    with pytest.warns(jaxfoam._scene.PlausibilityWarning, match="200,000 substeps per frame"):
        check_substeps(200_000, 2, 10 ** 6, span=0.1, dt=2.5e-7)
    with pytest.raises(BudgetError, match=r"2,000,000 substeps .* --max-substeps 2000000"):
        check_substeps(200_000, 10, 10 ** 6, span=0.1, dt=2.5e-7)


def _api(fn):
    try:
        fn()
    except ValueError as exc:
        return str(exc)
    raise AssertionError("no ValueError raised")


def _api_cases(files):
    from fitting import FitSettings, build_problem
    from fitting import synthesize

    scene = jaxfoam.load_scene(DROP_SPEC)
    return {
        "load_scene non-UTF-8 file": (lambda: jaxfoam.load_scene(files["latin1"]), ["latin1.json", "UTF-8"]),
        "load_scene missing file text": (lambda: jaxfoam.load_scene("nowhere.json"), ["nowhere.json", "no such file"]),
        "load_scene bad JSON text": (lambda: jaxfoam.load_scene('{"kind": '), ["not valid JSON"]),
        "load_trajectory NaN positions": (lambda: jaxfoam.load_trajectory(files["traj_nan"]),
                                          ["traj_nan.h5", "'/frames/x'", "non-finite"]),
        "load_trajectory truncated": (lambda: jaxfoam.load_trajectory(files["traj_cut"]), ["traj_cut.h5"]),
        "save_trajectory to a directory": (lambda: jaxfoam.save_trajectory(files["outdir"], _trajectory_parts()),
                                           ["outdir", "is a directory"]),
        "read_silhouettes corrupted chunk": (lambda: read_silhouettes(files["data_corrupt"]), ["'masks'", "damaged"]),
        "write_silhouettes to a directory": (lambda: read_silhouettes(files["data"]).write(files["outdir"]),
                                             ["outdir", "is a directory"]),
        "synthesize pixel size in um": (lambda: synthesize(scene, dict(mu=200, sigma_y=40, eta=10, m=0.5),
                                                           pixel_size=1e-6), ["pixel_size", "pixels"]),
        "synthesize negative seed": (lambda: synthesize(scene, dict(mu=200, sigma_y=40, eta=10, m=0.5), seed=-1),
                                     ["seed", ">= 0", "-1"]),
        "synthesize particle budget": (lambda: synthesize(scene, dict(mu=200, sigma_y=40, eta=10, m=0.5), dx=1e-4),
                                       ["dx", "particles", "max-particles"]),
        "build_problem pixel level": (lambda: build_problem(read_silhouettes(files["data"]), FitSettings(pixel_level=9)),
                                      ["pixel_level", "[0, 2]", "9"]),
        "build_problem no foam": (lambda: build_problem(read_silhouettes(files["data_empty"])), ["masks", "no foam"]),
        "build_problem all foam": (lambda: build_problem(read_silhouettes(files["data_full"])), ["masks", "every pixel"]),
        "build_problem pixel size": (lambda: build_problem(read_silhouettes(files["data_pixel10"])),
                                     ["camera.pixel_size"]),
        "build_problem ms times": (lambda: build_problem(read_silhouettes(files["data_ms"])),
                                   ["substeps", "milliseconds"]),
        "build_problem float32 overflow": (lambda: build_problem(read_silhouettes(files["data"]),
                                                                 FitSettings(dtype="float32", fixed={"kappa": 1e39})),
                                           ["kappa", "float32"]),
    }


API_NAMES = ["load_scene non-UTF-8 file", "load_scene missing file text", "load_scene bad JSON text",
             "load_trajectory NaN positions", "load_trajectory truncated", "save_trajectory to a directory",
             "read_silhouettes corrupted chunk", "write_silhouettes to a directory", "synthesize pixel size in um",
             "synthesize negative seed", "synthesize particle budget", "build_problem pixel level",
             "build_problem no foam", "build_problem all foam", "build_problem pixel size", "build_problem ms times",
             "build_problem float32 overflow"]


@pytest.mark.parametrize("name", API_NAMES)
def test_api_bad_input(name, files):
    fn, words = _api_cases(files)[name]
    msg = _api(fn)
    assert all(w in msg for w in words), f"{name}: {msg!r} lacks {words}"


def test_every_api_case_is_listed(files):
    assert sorted(_api_cases(files)) == sorted(API_NAMES)


def test_suite_has_at_least_100_cases():
    assert len(CLI_CASES) + len(BAD_SCENES) + len(API_NAMES) >= 100


def test_a_missing_output_directory_is_created_by_every_command(files, tmp_path, capsys):
    """One rule for every command: the output's parent directories are created (render shown here; simulate,
    synth, track and fit check their outputs with the same `check_output`)."""
    from jaxfoam.guards import check_output

    out = tmp_path / "new" / "deeper" / "sheet.png"
    assert cli.main(["render", str(files["traj"]), "--out", str(out), "--panels", "2"]) == 0
    assert out.stat().st_size > 1000
    assert [p.name for p in out.parent.iterdir()] == ["sheet.png"]  # no temporary file left beside it
    assert check_output(tmp_path / "a" / "b" / "x.h5") == str(tmp_path / "a" / "b" / "x.h5")
    assert (tmp_path / "a" / "b").is_dir()
