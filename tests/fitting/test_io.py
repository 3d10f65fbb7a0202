"""The silhouette format (shared/specs/silhouettes.md): round trip, and each bad file a clear error
naming its field."""
import json

import h5py
import numpy as np
import pytest

from fitting import Camera, SilhouetteFormatError, read_silhouettes, write_silhouettes
from fitting.io import camera_covering, glue_under_plates, plate_footprint
from jaxfoam import load_scene

from helpers import scene as zoo_scene

SCENE = zoo_scene("hanging_plate", initial_shape={"type": "first_mask"})
T, H, W = 3, 35, 30
CAMERA = Camera(pixel_size=0.01, origin=(-0.15, 0.0))


def _masks():
    m = np.zeros((T, H, W), np.uint8)
    m[:, 5:12, 10:20] = 1
    m[1, 12, 15] = 1
    return m


def _valid(path, **over):
    kw = dict(masks=_masks(), times=np.array([0.0, 0.1, 0.25]), camera=CAMERA, scene=SCENE,
              weights=None, source="unit test", truth={"mu": 100.0, "sigma_y": 30.0, "eta": 5.0, "m": 0.6,
                                                       "kappa": 2000.0})
    kw.update(over)
    write_silhouettes(path, kw.pop("masks"), kw.pop("times"), kw.pop("camera"), kw.pop("scene"), **kw)
    return path


def test_round_trip_keeps_every_field(tmp_path):
    w = np.full((T, H, W), 0.5, np.float32)
    w[:, 0, :] = 0.0
    w[2, 3, 4] = 1.0
    p = _valid(tmp_path / "a.h5", weights=w)
    d = read_silhouettes(p)
    assert d.masks.dtype == np.uint8 and d.masks.shape == (T, H, W)
    np.testing.assert_array_equal(d.masks, _masks())
    np.testing.assert_array_equal(d.times, [0.0, 0.1, 0.25])
    np.testing.assert_array_equal(d.weights, w)
    assert d.weights.dtype == np.float32
    assert d.camera == CAMERA
    assert d.scene_dict == SCENE
    assert d.source == "unit test"
    assert d.truth == {"mu": 100.0, "sigma_y": 30.0, "eta": 5.0, "m": 0.6, "kappa": 2000.0}
    assert d.load_scene().kind == "hanging_plate"
    mask0, cam = d.first_mask
    # the 70 foam pixels, and the 10 the sticky plate hides in the columns where the foam meets its face
    assert cam["pixel_size"] == 0.01 and mask0.sum() == 80
    np.testing.assert_array_equal(mask0[4, 10:20], 1)
    with h5py.File(p) as fh:  # the spec's layout, literally
        assert fh.attrs["format"] == "jaxfoam-silhouettes" and fh.attrs["version"] == 1
        assert fh["masks"].dtype == np.uint8 and fh["times"].dtype == np.float64
        assert fh["camera"].attrs["model"] == "orthographic" and fh["camera"].attrs["axis"] == "z"
        assert json.loads(fh["scene"].attrs["json"]) == SCENE


def test_weights_absent_or_2d_are_broadcast(tmp_path):
    d = read_silhouettes(_valid(tmp_path / "a.h5", truth=None))
    assert d.truth is None
    np.testing.assert_array_equal(d.weights, np.ones((T, H, W), np.float32))
    w2 = np.linspace(0, 1, H * W, dtype=np.float32).reshape(H, W)
    p = _valid(tmp_path / "b.h5", weights=w2)
    with h5py.File(p) as fh:
        assert fh["weights"].shape == (H, W)
    d = read_silhouettes(p)
    assert d.weights.shape == (T, H, W)
    np.testing.assert_array_equal(d.weights[2], w2)


def test_pixel_geometry_matches_the_spec():
    """Pixel (i, j) covers x in [x0 + j p, x0 + (j+1) p], y in [y0 + (H-1-i) p, y0 + (H-i) p]."""
    x, y = CAMERA.pixel_centers((H, W))
    assert x[0] == pytest.approx(-0.145) and x[-1] == pytest.approx(-0.15 + 29.5 * 0.01)
    assert y[0] == pytest.approx((H - 0.5) * 0.01) and y[-1] == pytest.approx(0.005)
    scene = load_scene(SCENE)
    cam, shape = camera_covering(scene, 0.01)
    assert shape == (35, 30) and cam.origin == (-0.15, 0.0)
    fp = plate_footprint(scene, 0.0, cam, shape)
    # plate x in [-0.08, 0.08] -> columns 7..22; y in [0.295, 0.305] -> rows from bottom 29, 30 -> image rows 5, 4
    rows, cols = np.nonzero(fp)
    assert set(rows.tolist()) == {4, 5} and cols.min() == 7 and cols.max() == 22


def _mutate(path, fn):
    with h5py.File(path, "r+") as fh:
        fn(fh)
    return path


def _replace(name, data):
    def fn(fh):
        del fh[name]
        fh.create_dataset(name, data=data)
    return fn


def _set_attr(group, key, value):
    def fn(fh):
        (fh if group == "/" else fh[group]).attrs[key] = value
    return fn


def _del(name):
    def fn(fh):
        del fh[name]
    return fn


def _scene_edit(**changes):
    spec = dict(SCENE, **changes)
    return _set_attr("scene", "json", json.dumps(spec))


BAD_FILES = {
    "format attr": (_set_attr("/", "format", "something-else"), "format"),
    "version attr": (_set_attr("/", "version", 2), "version"),
    "masks missing": (_del("masks"), "masks"),
    "masks 2D": (_replace("masks", np.zeros((H, W), np.uint8)), "masks"),
    "masks not 0/1": (_replace("masks", np.full((T, H, W), 2, np.uint8)), "masks"),
    "masks NaN": (_replace("masks", np.full((T, H, W), np.nan)), "masks"),
    "times count": (_replace("times", np.array([0.0, 0.1])), "times"),
    "times decreasing": (_replace("times", np.array([0.0, 0.2, 0.1])), "times"),
    "times repeated": (_replace("times", np.array([0.0, 0.1, 0.1])), "times"),
    "times NaN": (_replace("times", np.array([0.0, np.nan, 0.3])), "times"),
    "times negative": (_replace("times", np.array([-0.1, 0.1, 0.3])), "times"),
    "weights shape": (_replace("weights", np.ones((T, H, W + 1), np.float32)), "weights"),
    "weights above 1": (_replace("weights", np.full((H, W), 1.5, np.float32)), "weights"),
    "weights negative": (_replace("weights", np.full((H, W), -0.1, np.float32)), "weights"),
    "weights inf": (_replace("weights", np.full((H, W), np.inf, np.float32)), "weights"),
    "camera missing": (_del("camera"), "camera"),
    "camera model": (_set_attr("camera", "model", "perspective"), "camera.model"),
    "camera axis": (_set_attr("camera", "axis", "x"), "camera.axis"),
    "pixel_size zero": (_set_attr("camera", "pixel_size", 0.0), "camera.pixel_size"),
    "pixel_size NaN": (_set_attr("camera", "pixel_size", np.nan), "camera.pixel_size"),
    "origin 3 numbers": (_set_attr("camera", "origin", [0.0, 0.0, 0.0]), "camera.origin"),
    "origin missing": (lambda fh: fh["camera"].attrs.__delitem__("origin"), "camera.origin"),
    "camera misses domain": (_set_attr("camera", "origin", [100.0, 100.0]), "camera"),
    "scene missing": (_del("scene"), "scene.json"),
    "scene not json": (_set_attr("scene", "json", "{kind: drop"), "scene.json"),
    "scene unknown kind": (_scene_edit(kind="pour"), "kind"),
    "scene unknown key": (_scene_edit(colour="white"), "unknown key"),
    "scene bad density": (_scene_edit(density=-1.0), "density"),
    "first_mask empty": (_replace("masks", np.zeros((T, H, W), np.uint8)), "first mask"),
    "truth not a number": (_set_attr("truth", "mu", np.nan), "truth.mu"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_gives_clear_error_naming_the_field(tmp_path, case):
    fn, field = BAD_FILES[case]
    p = _valid(tmp_path / "bad.h5", weights=np.ones((H, W), np.float32))
    _mutate(p, fn)
    with pytest.raises(SilhouetteFormatError, match=r"bad\.h5") as info:
        read_silhouettes(p)
    assert field in str(info.value), str(info.value)
    assert isinstance(info.value, ValueError)


def test_not_hdf5_is_a_clear_error(tmp_path):
    p = tmp_path / "x.h5"
    p.write_text("not hdf5")
    with pytest.raises(SilhouetteFormatError, match="cannot open as HDF5"):
        read_silhouettes(p)


def test_writer_refuses_what_the_reader_refuses(tmp_path):
    with pytest.raises(SilhouetteFormatError, match="'times'.*strictly increasing"):
        _valid(tmp_path / "w.h5", times=np.array([0.0, 0.3, 0.2]))
    with pytest.raises(SilhouetteFormatError, match="camera.pixel_size"):
        _valid(tmp_path / "w.h5", camera={"model": "orthographic", "pixel_size": -1, "origin": [0, 0], "axis": "z"})
    with pytest.raises(SilhouetteFormatError, match="unknown kind"):
        _valid(tmp_path / "w.h5", scene=dict(SCENE, kind="pour"))
    assert not (tmp_path / "w.h5").exists()


def test_first_mask_continues_hanging_foam_into_the_sticky_plate():
    """A camera does not see foam behind a plate, yet a sticky plate holds only material that reaches its
    nodes. Foam that does not rest on the floor hangs from the plates it meets: the first mask is continued
    through the plate's covered pixels in the columns whose pixel just below the plate shows such foam, and
    in the rows whose pixel just beside it does. Foam standing on the floor under the plate, foam on the
    plate's top face and pixels away from the plate are left alone; a plate that is not sticky gets
    nothing."""
    scene = load_scene(SCENE)
    shape = (H, W)
    fp = plate_footprint(scene, 0.0, CAMERA, shape)
    rows, cols = np.nonzero(fp)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    assert (r0, r1, c0, c1) == (4, 6, 7, 23)
    mask = np.zeros(shape, np.uint8)
    mask[r1:r1 + 6, 10:14] = 1          # hangs below the bottom face in columns 10-13
    mask[r1 + 3, 8] = 1                  # a pixel that does not touch the plate
    mask[r0 + 1, c1:c1 + 3] = 1          # hangs on the right face in row 5
    mask[r1:, 19:22] = 1                 # a column standing on the floor (row H - 1) up to the plate
    mask[r0 - 2:r0, 15:17] = 1           # lies on the top face
    out = glue_under_plates(scene, mask, CAMERA, 0.0)
    assert out.dtype == np.uint8 and out.shape == shape
    added = (out > 0) & (mask == 0)
    expect = np.zeros(shape, bool)
    expect[r0:r1, 10:14] = True
    expect[r0 + 1, c0:c1] = True
    np.testing.assert_array_equal(added, expect)
    # a tracked video blanks a margin around the plate (weight 0): foam that starts below that margin is
    # continued through it; the same gap with weight 1 is seen to be empty, so nothing is filled
    gap = np.zeros(shape, np.uint8)
    gap[r1 + 2:r1 + 8, 10:14] = 1
    w = np.ones(shape, np.float32)
    w[r0 - 2:r1 + 2, c0 - 2:c1 + 2] = 0.0
    filled = glue_under_plates(scene, gap, CAMERA, 0.0, weights=w)
    expect = gap.astype(bool).copy()
    expect[r0:r1 + 2, 10:14] = True
    np.testing.assert_array_equal(filled > 0, expect)
    np.testing.assert_array_equal(glue_under_plates(scene, gap, CAMERA, 0.0, weights=np.ones(shape)), gap)
    np.testing.assert_array_equal(glue_under_plates(scene, gap, CAMERA, 0.0), gap)
    loose = load_scene(dict(SCENE, plate=dict(SCENE["plate"], sticky=False)))
    np.testing.assert_array_equal(glue_under_plates(loose, mask, CAMERA, 0.0), mask)
    empty = np.zeros(shape, np.uint8)
    np.testing.assert_array_equal(glue_under_plates(scene, empty, CAMERA, 0.0), empty)
