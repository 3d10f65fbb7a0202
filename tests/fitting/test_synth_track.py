"""Synthetic data (`jaxfoam synth`) and video tracking (`jaxfoam track`): files round-trip through the
silhouette format with their truth, and the tracker recovers a known silhouette sequence from a
video the test renders itself."""
import json
import warnings

import jax
import numpy as np
import pytest

from jaxfoam.cli import main
from fitting import Camera, read_silhouettes
from fitting.io import camera_covering, plate_footprint
from jaxfoam import load_scene
from fitting import synthesize
from fitting.synth import boundary_pixels, parse_params
from fitting.track import closing, dilate, fill_holes, label_components, largest_component, opening, otsu_threshold

HANGING = {
    "kind": "hanging_plate", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 2000.0,
    "domain": {"min": [-0.12, 0.0], "max": [0.12, 0.3]}, "floor": {"y": 0.0, "friction": 0.5},
    "plate": {"center": [0.0, 0.25], "half_size": [0.07, 0.01],
              "motion": {"type": "sinusoid", "axis": [1.0, 0.0], "amplitude": 0.01, "frequency": 3.0,
                         "phase": 0.0, "ramp_time": 0.05}},
    "initial_shape": {"type": "ellipse", "center": [0.0, 0.19], "radii": [0.06, 0.055]},
}
PARAMS = {"mu": 150.0, "sigma_y": 40.0, "eta": 8.0, "m": 0.6}
# Tiny on purpose: 4 frames over 0.09 s at dx = 2 cm (the compiled rollout is shared by both runs).
SYNTH = dict(dx=0.02, frames=4, duration=0.09, pixel_size=0.005, drop_frames=0.34, seed=3)


def _iou(a, b):
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.fixture(scope="module")
def synth_clean(tmp_path_factory):
    """Noise-free synthetic data written by the command line."""
    d = tmp_path_factory.mktemp("synth")
    scene = d / "scene.json"
    scene.write_text(json.dumps(HANGING))
    out = d / "clean.h5"
    rc = main(["synth", str(scene), "--params", ",".join(f"{k}={v}" for k, v in PARAMS.items()), "--out", str(out),
               "--dx", str(SYNTH["dx"]), "--frames", str(SYNTH["frames"]), "--duration", str(SYNTH["duration"]),
               "--pixel-size", str(SYNTH["pixel_size"]), "--noise", "0", "--drop-frames", str(SYNTH["drop_frames"]),
               "--seed", str(SYNTH["seed"])])
    assert rc == 0
    return read_silhouettes(out)


@pytest.mark.slow
def test_synth_file_round_trips_with_truth_and_gaps(synth_clean):
    d = synth_clean
    assert d.truth == dict(PARAMS, kappa=2000.0, rho=80.0)
    # 4 frames on [0, 0.09] s, one of the three after t = 0 dropped: times with a gap, t = 0 kept.
    grid = np.linspace(0.0, 0.09, 4)
    assert len(d.times) == 3 and d.times[0] == 0.0
    assert np.all(np.isin(d.times, grid))
    assert d.scene_dict == HANGING
    src = json.loads(d.source)
    assert src["generator"] == "jaxfoam synth" and src["dx"] == 0.02 and src["substeps"] >= 1
    scene = load_scene(HANGING)
    cam, shape = camera_covering(scene, 0.005)
    assert d.camera == cam and d.image_shape == shape == (60, 48)


@pytest.mark.slow
def test_synth_hides_the_plate_with_zero_weight(synth_clean):
    """Plate pixels (its footprint at each frame's time, Plate.position(t)) have weight 0 and mask 0;
    every other pixel weight 1."""
    d = synth_clean
    scene = d.load_scene()
    for t, time in enumerate(d.times):
        fp = plate_footprint(scene, float(time), d.camera, d.image_shape)
        assert fp.sum() > 0
        np.testing.assert_array_equal(d.weights[t] == 0, fp)
        assert not d.masks[t][fp].any()
        assert np.all(d.weights[t][~fp] == 1.0)


@pytest.mark.slow
def test_synth_first_frame_is_the_initial_shape(synth_clean):
    """Frame 0 without noise is the sampled ellipse (minus the plate): IoU > 0.9 at dx = 2 cm, and the
    cream hangs below the plate in every frame."""
    d = synth_clean
    cam = d.camera
    xc, yc = cam.pixel_centers(d.image_shape)
    X, Y = np.meshgrid(xc, yc)
    ellipse = (X / 0.06) ** 2 + ((Y - 0.19) / 0.055) ** 2 <= 1
    fp = plate_footprint(d.load_scene(), 0.0, cam, d.image_shape)
    assert _iou(d.masks[0], ellipse & ~fp) > 0.9
    for t in range(len(d.times)):
        ys = Y[d.masks[t] > 0]
        assert ys.max() < 0.25 and ys.min() > 0.1


@pytest.mark.slow
def test_synth_noise_flips_boundary_pixels_only(synth_clean, tmp_path):
    """With noise p, pixels flip only on either side of the clean boundary, about a fraction p of
    them; the frames dropped do not depend on the noise; --first-mask records the mask as the shape."""
    clean = synth_clean
    p = 0.3
    noisy = synthesize(HANGING, PARAMS, noise=p, first_mask=True, **SYNTH)
    np.testing.assert_array_equal(noisy.times, clean.times)
    flipped = noisy.masks != clean.masks
    band = np.stack([boundary_pixels(m) for m in clean.masks]) & (clean.weights > 0)
    assert not np.any(flipped & ~band)
    frac = flipped[band].mean()
    assert abs(frac - p) < 0.1, frac
    assert noisy.scene_dict["initial_shape"] == {"type": "first_mask"}
    noisy.write(tmp_path / "noisy.h5")
    again = read_silhouettes(tmp_path / "noisy.h5")
    np.testing.assert_array_equal(again.masks, noisy.masks)


@pytest.mark.slow
def test_synth_cfl_sets_the_data_time_step_not_the_motion(synth_clean):
    """`cfl` (another simulator's time step): the substeps scale as 1 / CFL (ceil) and are recorded in
    the file's source; the silhouettes are those of the same motion (IoU > 0.95 against CFL 0.3)."""
    src0 = json.loads(synth_clean.source)
    assert src0["cfl"] == 0.3
    d = synthesize(HANGING, PARAMS, noise=0.0, cfl=0.6, **SYNTH)
    src = json.loads(d.source)
    assert src["cfl"] == 0.6
    assert src["substeps"] == pytest.approx(src0["substeps"] / 2, abs=1)
    np.testing.assert_array_equal(d.times, synth_clean.times)
    for a, b in zip(d.masks, synth_clean.masks):
        assert _iou(a, b) > 0.95
    with pytest.raises(ValueError, match="cfl"):
        synthesize(HANGING, PARAMS, cfl=1.5, **SYNTH)


def test_synth_rejects_bad_requests():
    with pytest.raises(ValueError, match="missing"):
        parse_params("mu=1,sigma_y=2")
    with pytest.raises(ValueError, match="kappa is a known input"):
        parse_params("mu=1,sigma_y=2,eta=1,m=0.5,kappa=3")
    with pytest.raises(ValueError, match="unknown parameter 'nu'"):
        parse_params("mu=1,sigma_y=2,eta=1,m=0.5,nu=3")
    with pytest.raises(ValueError, match="Params.m"):
        synthesize(HANGING, dict(PARAMS, m=-1.0), **SYNTH)
    with pytest.raises(ValueError, match="first_mask"):
        synthesize(dict(HANGING, initial_shape={"type": "first_mask"}), PARAMS, **SYNTH)
    with pytest.raises(ValueError, match="noise"):
        synthesize(HANGING, PARAMS, noise=1.5, **SYNTH)


# ----------------------------------------------------------------------------------------------
# Tracking
# ----------------------------------------------------------------------------------------------

def test_connected_components_match_a_flood_fill():
    """Run-length labeling against scipy.ndimage.label (4- and 8-connectivity), holes against
    binary_fill_holes, on random blobby masks."""
    ndi = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(0)
    for shape in ((37, 53), (64, 41)):
        m = ndi.binary_opening(rng.random(shape) < 0.55)
        for conn, structure in ((4, ndi.generate_binary_structure(2, 1)), (8, ndi.generate_binary_structure(2, 2))):
            lab, sizes = label_components(m, conn)
            ref, n = ndi.label(m, structure)
            assert len(sizes) == n
            assert len(set(zip(lab[m].tolist(), ref[m].tolist()))) == n  # the same partition
            np.testing.assert_array_equal(np.sort(sizes), np.sort(np.bincount(ref.ravel())[1:]))
        np.testing.assert_array_equal(fill_holes(m), ndi.binary_fill_holes(m))
        big = largest_component(m)
        assert big.sum() == np.bincount(ndi.label(m, ndi.generate_binary_structure(2, 2))[0].ravel())[1:].max()


def test_morphology_removes_specks_and_bridges_cracks():
    m = np.zeros((40, 40), bool)
    yy, xx = np.indices(m.shape)
    disk = (yy - 20) ** 2 + (xx - 20) ** 2 <= 100
    m |= disk
    m[3, 3] = True  # a speck
    cracked = disk.copy()
    cracked[14:27, 20] = False  # a one-pixel crack inside the disk
    assert not opening(m, 1)[3, 3]
    np.testing.assert_array_equal(opening(m, 1), opening(disk, 1))
    assert np.sum(disk & ~opening(disk, 1)) <= 8  # only the digital disk's four tips are shaved
    np.testing.assert_array_equal(closing(cracked, 1), closing(disk, 1))
    assert np.all(closing(disk, 1) >= disk)
    assert dilate(np.eye(5, dtype=bool), 1).sum() == 13  # the diagonal and its two neighbouring diagonals


def test_otsu_splits_two_populations():
    rng = np.random.default_rng(1)
    v = np.concatenate([rng.normal(0.1, 0.03, 5000), rng.normal(0.7, 0.05, 1000)])
    assert 0.2 < otsu_threshold(v) < 0.6


def _ellipse_video(T=30, H=96, W=128, p=0.002, origin=(-0.128, 0.0)):
    """A white ellipse moving over a textured static background: frames (T, H, W, 3) uint8 and the
    known masks (pixel centres inside the ellipse)."""
    cam = Camera(p, origin)
    xc, yc = cam.pixel_centers((H, W))
    X, Y = np.meshgrid(xc, yc)
    bg = 60 + 50 * (X - X.min()) / np.ptp(X) + 25 * np.sin(X / 0.013) * np.cos(Y / 0.017)
    frames, masks = [], []
    for k in range(T):
        s = k / (T - 1)
        cx, cy = -0.085 + 0.17 * s, 0.095 + 0.03 * np.sin(2 * np.pi * s)
        inside = ((X - cx) / 0.03) ** 2 + ((Y - cy) / 0.022) ** 2 <= 1
        img = np.where(inside, 225 + 15 * (Y - cy) / 0.022, bg)
        frames.append(np.repeat(np.clip(img, 0, 255).astype(np.uint8)[..., None], 3, axis=2))
        masks.append(inside)
    return np.stack(frames), np.stack(masks), cam


DROP = {"kind": "drop", "dim": 2, "density": 80.0, "kappa": 2000.0,
        "domain": {"min": [-0.128, 0.0], "max": [0.128, 0.192]}, "floor": {"y": 0.0, "friction": 0.5},
        "initial_shape": {"type": "first_mask"}}


def test_track_recovers_a_moving_ellipse_from_mp4(tmp_path):
    """An H.264 video (lossy) at 10 fps: median background, Otsu, clean-up, largest component.
    Every frame's silhouette matches the drawn ellipse with IoU > 0.95; times are k / fps."""
    iio = pytest.importorskip("imageio.v3")
    pytest.importorskip("imageio_ffmpeg")
    frames, known, cam = _ellipse_video()
    video = tmp_path / "foam.mp4"
    jax.devices()  # JAX's at-fork warning hook is installed with its backend
    with warnings.catch_warnings(record=True) as raw:
        warnings.simplefilter("always")
        iio.imwrite(video, frames, fps=10)  # plain imageio: ffmpeg's subprocess trips JAX's fork warning
    assert any("os.fork" in str(w.message) for w in raw)  # so the check below can fail
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(DROP))
    out = tmp_path / "tracked.h5"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        rc = main(["track", str(video), "--out", str(out), "--scene", str(scene), "--pixel-size", "0.002",
                   "--origin", "-0.128", "0.0"])
    assert rc == 0
    # Reading the video runs ffmpeg in a subprocess too; the tracker silences JAX's fork warning for it.
    assert not [str(w.message) for w in seen if "os.fork" in str(w.message)]
    d = read_silhouettes(out)
    assert d.masks.shape == known.shape
    np.testing.assert_allclose(d.times, np.arange(len(known)) / 10.0, atol=1e-9)
    assert d.camera == cam
    ious = [_iou(d.masks[t], known[t]) for t in range(len(known))]
    assert min(ious) > 0.95, ious


def test_track_image_directory_with_brightness_threshold_and_plate(tmp_path):
    """A PNG sequence (lossless) thresholded on brightness (background up to 0.53, foam above 0.82 of
    full intensity), every second frame, 2x downsampling; the scene's plate footprint (dilated by
    the margin) gets weight 0."""
    iio = pytest.importorskip("imageio.v3")
    frames, known, cam = _ellipse_video(T=8)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, f in enumerate(frames):
        iio.imwrite(folder / f"frame_{k:03d}.png", f)
    scene = dict(DROP, kind="hanging_plate", initial_shape={"type": "ellipse", "center": [0.0, 0.1],
                                                            "radii": [0.03, 0.02]},
                 plate={"center": [0.0, 0.17], "half_size": [0.05, 0.005]})
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(json.dumps(scene))
    out = tmp_path / "tracked.h5"
    rc = main(["track", str(folder), "--out", str(out), "--scene", str(scene_file), "--pixel-size", "0.002",
               "--origin", "-0.128", "0.0", "--background", "none", "--threshold", "0.56", "--fps", "25",
               "--every", "2", "--downsample", "2"])
    assert rc == 0
    d = read_silhouettes(out)
    assert d.masks.shape == (4, 48, 64) and d.camera.pixel_size == pytest.approx(0.004)
    np.testing.assert_allclose(d.times, [0.0, 0.08, 0.16, 0.24])
    for t in range(4):
        coarse = known[2 * t].reshape(48, 2, 64, 2).mean(axis=(1, 3)) >= 0.5
        # 15 x 11 pixels after downsampling: ~40 half-covered boundary pixels decide on the local
        # background brightness, so IoU 0.9 is what a correct pipeline gets.
        assert _iou(d.masks[t], coarse) > 0.9
        fp = dilate(plate_footprint(load_scene(scene), float(d.times[t]), d.camera, (48, 64)), 2)
        np.testing.assert_array_equal(d.weights[t] == 0, fp)


def test_track_errors_are_clear(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(DROP))
    folder = tmp_path / "empty"
    folder.mkdir()
    base = ["--out", str(tmp_path / "o.h5"), "--scene", str(scene), "--pixel-size", "0.002", "--origin", "0", "0"]
    assert main(["track", str(folder)] + base) == 2  # no image in the directory
    assert main(["track", str(tmp_path / "missing.mp4")] + base) == 2
    assert not (tmp_path / "o.h5").exists()
