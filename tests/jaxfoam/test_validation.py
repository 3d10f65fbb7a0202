"""Bad input fails early with a ValueError that names the field and what it should be.

Three doors: `Params.validate` (and everything that takes Params), `load_scene` (scene description of
shared/specs/silhouettes.md: SceneError, a ValueError), and `simulate` / `Simulator` arguments.
"""
import json
import math

import numpy as np
import pytest

from jaxfoam import Params, SceneError, Simulator, load_scene, simulate

from helpers import edited, scene as zoo_scene

GOOD = dict(mu=300.0, kappa=2000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)  # Pa, Pa, Pa, Pa s^m, -, kg/m^3

SCENE = zoo_scene("hanging_plate")


# ------------------------------------------------------------------------------------------------
# Params
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("field, value, expected_range", [
    ("mu", 0.0, "> 0 Pa"), ("mu", -1.0, "> 0 Pa"), ("mu", math.nan, "> 0 Pa"), ("mu", math.inf, "> 0 Pa"),
    ("kappa", 0.0, "> 0 Pa"), ("kappa", -5.0, "> 0 Pa"), ("kappa", math.nan, "> 0 Pa"),
    ("rho", 0.0, "> 0 kg/m^3"), ("rho", -80.0, "> 0 kg/m^3"), ("rho", math.nan, "> 0 kg/m^3"),
    ("sigma_y", -1e-3, ">= 0 Pa"), ("sigma_y", math.nan, ">= 0 Pa"),
    ("eta", -1.0, ">= 0 Pa s^m"), ("eta", math.nan, ">= 0 Pa s^m"),
    ("m", 0.0, "in (0, 5]"), ("m", -0.5, "in (0, 5]"), ("m", 5.0001, "in (0, 5]"), ("m", math.nan, "in (0, 5]"),
])
def test_bad_params_name_field_and_range(field, value, expected_range):
    params = Params(**{**GOOD, field: value})
    with pytest.raises(ValueError) as info:
        params.validate()
    msg = str(info.value)
    assert f"Params.{field}" in msg and expected_range in msg, msg
    # Every entry point that takes Params validates them before any work.
    with pytest.raises(ValueError, match=rf"Params\.{field}"):
        simulate(load_scene(SCENE), params, [0.01], dx=0.02)


def test_good_params_and_edges_are_accepted():
    """The closed ends of the ranges are valid: sigma_y = 0, eta = 0, m = 5; arrays are checked elementwise."""
    Params(**GOOD).validate()
    Params(**{**GOOD, "sigma_y": 0.0, "eta": 0.0, "m": 5.0}).validate()
    with pytest.raises(ValueError, match=r"Params\.mu"):
        Params(**{**GOOD, "mu": np.array([1.0, -1.0])}).validate()
    with pytest.raises(ValueError, match=r"Params\.eta must be a real number"):
        Params(**{**GOOD, "eta": "five"}).validate()


def test_params_are_checked_under_grad_and_pass_through_jit():
    """Under jax.grad (outside jit) the parameters still have values, and a bad one is named before any
    simulation work, as for concrete input; inside jit there are no values, and validation lets them pass."""
    import jax

    def twice_mu(p):
        p.validate()
        return 2.0 * p.mu

    assert float(jax.grad(twice_mu)(Params(**GOOD)).mu) == 2.0
    with pytest.raises(ValueError, match=r"Params\.m must be in \(0, 5\], got 7"):
        jax.grad(twice_mu)(Params(**{**GOOD, "m": 7.0}))
    with pytest.raises(ValueError, match=r"Params\.mu"):
        jax.grad(lambda p: simulate(load_scene(SCENE), p, [0.01], dx=0.02).frames["x"].sum())(
            Params(**{**GOOD, "mu": -1.0}))
    assert float(jax.jit(twice_mu)(Params(**{**GOOD, "m": 7.0}))) == 600.0


# ------------------------------------------------------------------------------------------------
# Scene descriptions
# ------------------------------------------------------------------------------------------------

def _edit(path, value, delete=False):
    """A copy of SCENE with the entry at `path` (keys/indices) set to value, or deleted."""
    return edited(SCENE, path, value, delete)


SAMPLES = {"type": "samples", "times": [0.0, 0.2, 0.2], "positions": [[0.0, 0.3], [0.01, 0.3], [0.0, 0.3]]}

BAD_SCENES = {
    # name: (scene, words the message must contain)
    "unknown kind": (_edit(["kind"], "splash"), ["'kind'", "splash", "hanging_plate"]),
    "unknown top-level key": (_edit(["colour"], "white"), ["'scene'", "colour"]),
    "unknown plate key": (_edit(["plate", "colour"], 1), ["'plate'", "colour"]),
    "unknown motion key": (_edit(["plate", "motion", "amp"], 0.01), ["'plate.motion'", "amp"]),
    "unknown motion type": (_edit(["plate", "motion", "type"], "circle"), ["'plate.motion.type'", "circle"]),
    "unknown floor key": (_edit(["floor", "mu"], 0.5), ["'floor'", "mu"]),
    "unknown initial_shape key": (_edit(["initial_shape", "radius"], 0.1), ["'initial_shape'", "radius"]),
    "unknown initial_shape type": (_edit(["initial_shape"], {"type": "blob"}), ["'initial_shape.type'", "blob"]),
    "dim 4": (_edit(["dim"], 4), ["'dim'", "2 or 3"]),
    "dim as text": (_edit(["dim"], "2"), ["'dim'", "2 or 3"]),
    "dim true": (_edit(["dim"], True), ["'dim'", "2 or 3"]),
    "3-vector in 2D": (_edit(["gravity"], [0.0, -9.81, 0.0]), ["'gravity'", "2 numbers"]),
    "short plate centre": (_edit(["plate", "center"], [0.0]), ["'plate.center'", "2 numbers"]),
    "short box corner": (_edit(["initial_shape", "max"], [0.05]), ["'initial_shape.max'", "2 numbers"]),
    "non-finite vector": (_edit(["plate", "center"], [float("nan"), 0.3]), ["'plate.center'", "finite"]),
    "non-increasing sample times": (_edit(["plate", "motion"], SAMPLES), ["'plate.motion.times'", "increasing"]),
    "domain max <= min": (_edit(["domain", "max"], [0.15, 0.0]), ["'domain'", "max must exceed min"]),
    "missing density": (_edit(["density"], None, delete=True), ["'density'", "required"]),
    "missing initial_shape": (_edit(["initial_shape"], None, delete=True), ["'initial_shape'", "required"]),
    "missing domain max": (_edit(["domain", "max"], None, delete=True), ["'domain'", "max"]),
    "missing plate centre": (_edit(["plate", "center"], None, delete=True), ["'plate.center'", "required"]),
    "hanging_plate without plate": (_edit(["plate"], None, delete=True), ["'plate'", "exactly one plate"]),
    "density <= 0": (_edit(["density"], 0.0), ["'density'", "> 0"]),
    "kappa not a number": (_edit(["kappa"], "stiff"), ["'kappa'", "number"]),
    "negative friction": (_edit(["floor", "friction"], -0.1), ["'floor.friction'", ">= 0"]),
    "zero half size": (_edit(["plate", "half_size"], [0.08, 0.0]), ["'plate.half_size'", "> 0"]),
    "sticky not boolean": (_edit(["plate", "sticky"], "yes"), ["'plate.sticky'", "true or false"]),
    "plate and plates": (_edit(["plates"], [SCENE["plate"]]), ["'plates'", "not both"]),
    "squeeze without plates": ({**_edit(["plate"], None, delete=True), "kind": "squeeze"},
                               ["'plates'", "at least one"]),
}


@pytest.mark.parametrize("name", sorted(BAD_SCENES))
def test_bad_scene_names_field(name):
    spec, words = BAD_SCENES[name]
    for form in (spec, json.dumps(spec)):  # a dict and its JSON text fail alike
        with pytest.raises(SceneError) as info:
            load_scene(form)
        msg = str(info.value)
        assert all(w in msg for w in words), f"{name}: {msg!r} lacks {words}"
    assert issubclass(SceneError, ValueError)


@pytest.mark.parametrize("text", ['{"kind": "drop", "dim": 2,', '{"kind": "drop"} trailing', "{'kind': 'drop'}"])
def test_bad_json_text(text):
    with pytest.raises(SceneError, match="not valid JSON"):
        load_scene(text)


def test_scene_file_errors(tmp_path):
    """A path to a missing file, or to a file with bad JSON, fails with the file named."""
    with pytest.raises(SceneError, match="cannot read file"):
        load_scene(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"kind": "drop",')
    with pytest.raises(SceneError, match="not valid JSON"):
        load_scene(bad)
    good = tmp_path / "good.json"
    good.write_text(json.dumps(SCENE))
    assert load_scene(good).kind == "hanging_plate"


def test_good_scene_parses():
    """The reference scene (and its JSON text) parses, with its values."""
    scene = load_scene(json.dumps(SCENE))
    assert scene.kind == "hanging_plate" and scene.dim == 2 and len(scene.plates) == 1
    assert scene.domain_min == (-0.15, 0.0) and scene.floor_y == 0.0
    np.testing.assert_allclose(np.asarray(scene.gravity), [0.0, -9.81])


# ------------------------------------------------------------------------------------------------
# simulate / Simulator arguments
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, words", [
    (dict(dx=0.0), ["dx", "positive"]),
    (dict(dx=-0.01), ["dx", "positive"]),
    (dict(dx=math.nan), ["dx", "positive"]),
    (dict(frame_times=[0.02, 0.01]), ["frame_times", "increasing"]),
    (dict(frame_times=[0.01, 0.01]), ["frame_times", "increasing"]),
    (dict(frame_times=[0.0, 0.01]), ["frame_times", "after the start time"]),
    (dict(frame_times=[]), ["frame_times", "non-empty"]),
    (dict(frame_times=[0.01, math.nan]), ["frame_times", "finite"]),
    (dict(cfl=1.5), ["cfl", "(0, 1]"]),
    (dict(cfl=0.0), ["cfl", "(0, 1]"]),
    (dict(dtype=np.float16), ["dtype", "float32 or float64"]),
    (dict(substeps=0), ["substeps", ">= 1"]),
    (dict(ppc=0), ["ppc", ">= 1"]),
])
def test_bad_simulate_arguments(kwargs, words):
    args = dict(frame_times=[0.01, 0.02], dx=0.02)
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        simulate(load_scene(SCENE), Params(**GOOD), **args)
    msg = str(info.value)
    assert all(w in msg for w in words), f"{msg!r} lacks {words}"


def test_simulator_rejects_first_mask_scene_without_mask():
    """initial_shape 'first_mask' needs the mask: a clear error, not a crash."""
    spec = _edit(["initial_shape"], {"type": "first_mask"})
    with pytest.raises(SceneError, match="first_mask"):
        Simulator(load_scene(spec), [0.01], Params(**GOOD), dx=0.02)
