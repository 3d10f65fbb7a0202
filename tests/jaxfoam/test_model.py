"""The simulator core's contracts: `make_model` / `Model`, `jaxfoam.step`, `jaxfoam.rollout` (jit, vmap,
several models in one program), the adjoint objects, the backend tuning, the error base class, and
that importing jaxfoam leaves JAX's configuration alone."""
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam as jf
from jaxfoam._xla_cpu import PLAIN, XLA_CPU, Tuning, tuning_for

SCENES = pathlib.Path(__file__).parents[2] / "experiments" / "scenes"
PARAMS = jf.Params(mu=200.0, kappa=2000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)
TIMES = np.array([0.004, 0.008])


@pytest.fixture(scope="module")
def drop():
    scene = jf.load_scene(SCENES / "drop_2d.json")
    model = jf.make_model(scene, 0.02, params_ref=PARAMS, frame_times=TIMES)
    return model, model.sample()


def test_make_model_owns_the_cfl_step_and_frame_plan(drop):
    """dt = widest interval / substeps <= the CFL step cfl dx / (c + speed bound), with the fewest
    substeps that achieve it; without frame times dt is the CFL step itself."""
    model, _ = drop
    c = float(np.sqrt((PARAMS.kappa + 4 / 3 * PARAMS.mu) / PARAMS.rho))
    assert model.dt_cfl == pytest.approx(jf.CFL * 0.02 / (c + model.max_speed), rel=1e-12)
    assert model.dt <= model.dt_cfl * (1 + 1e-12)
    assert 0.004 / (model.substeps - 1) > model.dt_cfl
    assert model.substeps * model.dt == pytest.approx(0.004, rel=1e-12)
    free = jf.make_model(model.scene, 0.02, params_ref=PARAMS)
    assert free.substeps is None and free.dt == free.dt_cfl == model.dt_cfl


@pytest.mark.parametrize("kwargs,match", [
    (dict(dx=0.0), "dx must be a positive grid spacing in m, got 0.0"),
    (dict(dx=0.02, cfl=1.5), r"cfl must be in \(0, 1\], got 1.5"),
    (dict(dx=0.02, dtype="float16"), "dtype must be float32 or float64, got float16"),
    (dict(dx=0.02, substeps=0), "substeps must be an integer >= 1, got 0"),
    (dict(dx=0.02, dt=-1.0), "dt must be a positive time step in s, got -1.0"),
    (dict(dx=0.02, frame_times=[0.02, 0.01]), "frame_times must be strictly increasing"),
])
def test_make_model_names_the_bad_argument(drop, kwargs, match):
    with pytest.raises(jf.ModelError, match=match):
        jf.make_model(drop[0].scene, params_ref=PARAMS, **kwargs)


@pytest.mark.slow
def test_step_jits_with_the_model_as_an_argument(drop):
    """jax.jit(jaxfoam.step) needs no factory: the model is a pytree whose static part is its treedef.
    It equals the step with the model closed over, and a second call with a model of another dt (a
    data leaf) reuses the compiled program."""
    model, s0 = drop
    step = jax.jit(jf.step)
    a = step(model, s0, PARAMS)
    b = jax.jit(lambda s: jf.step(model, s, PARAMS))(s0)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-15)
    assert float(a.t) == pytest.approx(model.dt, rel=1e-15)
    c = step(model.replace(dt=0.5 * model.dt), s0, PARAMS)
    assert float(c.t) == pytest.approx(0.5 * model.dt, rel=1e-15)
    assert step._cache_size() == 1


@pytest.mark.slow
def test_rollout_vmaps_over_parameters_and_initial_states(drop):
    """jax.vmap of jaxfoam.rollout over (params, state0) gives each member's own rollout (1e-12 m)."""
    model, s0 = drop
    mus = jnp.asarray([150.0, 400.0])
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), s0)
    states = states.replace(v=states.v.at[1].add(jnp.asarray([0.1, 0.0])))

    def final_x(mu, s):
        return jf.rollout(model, s, PARAMS.replace(mu=mu), TIMES)[1]["x"]

    ens = jax.jit(jax.vmap(final_x))(mus, states)
    for k in range(2):
        one = final_x(mus[k], jax.tree_util.tree_map(lambda a: a[k], states))
        np.testing.assert_allclose(ens[k], one, rtol=0, atol=1e-12)
    assert float(jnp.max(jnp.abs(ens[0] - ens[1]))) > 1e-5


@pytest.mark.slow
def test_one_program_holds_several_models():
    """Two scenes (2D drop and hanging plate, different grids and substeps) in one jitted function:
    each equals its own rollout."""
    models = []
    for name, dx in (("drop_2d.json", 0.02), ("hanging_plate_2d.json", 0.015)):
        m = jf.make_model(jf.load_scene(SCENES / name), dx, params_ref=PARAMS, frame_times=TIMES)
        models.append((m, m.sample()))

    @jax.jit
    def both(p):
        return [jf.rollout(m, s, p, TIMES)[1]["x"][-1].mean(axis=0) for m, s in models]

    out = both(PARAMS)
    for (m, s), o in zip(models, out):
        np.testing.assert_allclose(o, jf.rollout(m, s, PARAMS, TIMES)[1]["x"][-1].mean(axis=0), rtol=1e-13)
    assert models[0][0].substeps != models[1][0].substeps or models[0][0].grid != models[1][0].grid


@pytest.mark.slow
def test_rollout_checks_concrete_inputs_before_any_compute(drop):
    """Parameters out of range, frame intervals wider than the model's substeps allow, and parameters
    whose wave speed puts the substep past the Courant limit are refused, each naming the quantity;
    traced stiff parameters are flagged in the health record, which Simulator.check reports."""
    model, s0 = drop
    with pytest.raises(ValueError, match=r"Params.m must be in \(0, 5\], got 0.0"):
        jf.rollout(model, s0, PARAMS.replace(m=0.0), TIMES)
    with pytest.raises(ValueError, match="Params.mu must be > 0 Pa, got -1.0"):
        jf.rollout(model, s0, PARAMS.replace(mu=-1.0), TIMES)
    with pytest.raises(jf.ModelError, match="frame interval 0.008 s needs more than"):
        jf.rollout(model, s0, PARAMS, [0.008])
    stiff = PARAMS.replace(mu=1e6)
    with pytest.raises(jf.ModelError, match="exceeds the stability bound .* params_ref"):
        jf.rollout(model, s0, stiff, TIMES)
    _, frames, health = jax.jit(lambda p: jf.rollout(model, s0, p, TIMES))(stiff)
    assert not bool(np.asarray(health[0])[:, -1].any())
    sim = jf.Simulator(model.scene, TIMES, PARAMS, dx=0.02)
    with pytest.raises(jf.SimulationError, match="Courant number above the model's limit"):
        sim.check(jax.device_get(frames), health)
    ok = jax.jit(lambda p: jf.rollout(model, s0, p, TIMES))(PARAMS)[2]
    assert bool(np.asarray(ok[0]).all())


def test_adjoints_validate_their_options():
    with pytest.raises(ValueError, match="ForwardMode.tangents must be one of"):
        jf.ForwardMode(tangents="batched")
    with pytest.raises(ValueError, match="ForwardMode.threads must be an integer >= 1"):
        jf.ForwardMode(threads=0)
    with pytest.raises(ValueError, match="frame_tape_bytes must be a positive number"):
        jf.Checkpointed(frame_tape_bytes=-1)
    with pytest.raises(ValueError, match="adjoint must be one of"):
        jf.rollout(None, None, PARAMS, TIMES, adjoint="rev")
    assert jf.HandWritten().hand_adjoint and not jf.Checkpointed().hand_adjoint
    assert hash(jf.HandWritten()) == hash(jf.HandWritten())


def test_tuning_per_backend_and_named_buffer_points():
    """XLA:CPU gets every buffer point and switch; other backends the plain path; an unknown buffer
    name is refused when the tuning is built and when a stage asks for it."""
    assert tuning_for("cpu") == XLA_CPU and tuning_for("gpu") == PLAIN and tuning_for("tpu") == PLAIN
    assert PLAIN.buffers == frozenset() and not PLAIN.halley_low_precision and not PLAIN.sort_by_cell
    with pytest.raises(ValueError, match="unknown buffer points"):
        Tuning(buffers={"g2p_tabel"})
    with pytest.raises(ValueError, match="is not a buffer point"):
        XLA_CPU.buffer("return_map", jnp.ones(2), 0.0)  # a tangent point asked for as a value buffer
    x = jnp.arange(3.0)
    assert PLAIN.buffer("g2p_table", x, 0.0) is x  # off: the identity, no cond
    hlo = jax.jit(lambda a, t: XLA_CPU.buffer("g2p_table", a * 2.0, t)).lower(x, 0.0).compile().as_text()
    assert "conditional(" in hlo


def test_errors_share_one_base_class():
    from fitting import CalibrationError
    from fitting import SilhouetteFormatError
    for cls in (jf.SceneError, jf.ModelError, jf.SimulationError, jf.TrajectoryError, CalibrationError,
                SilhouetteFormatError):
        assert issubclass(cls, jf.JaxfoamError), cls
    assert issubclass(jf.SceneError, ValueError) and issubclass(jf.SimulationError, FloatingPointError)


@pytest.mark.slow
def test_import_leaves_the_jax_configuration_alone():
    """A fresh process: importing jaxfoam keeps float64 off, and asking for float64 then is a clear
    ModelError that says how to enable it; float32 runs."""
    code = ("import jax, numpy as np, jaxfoam as jf\n"
            "assert not jax.config.jax_enable_x64\n"
            "s = jf.load_scene('%s', dtype=np.float32)\n"
            "p = jf.Params(mu=200.0, kappa=2000.0, sigma_y=20.0, eta=5.0, m=0.5, rho=80.0)\n"
            "m = jf.make_model(s, 0.05, params_ref=p, dtype=np.float32)\n"
            "jf.step(m, m.sample(), p)\n"
            "try:\n    jf.make_model(s, 0.05, params_ref=p)\n"
            "except jf.ModelError as e:\n    print(e)\n" % (SCENES / "drop_2d.json"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "dtype float64 needs jax.config.update('jax_enable_x64', True)" in out.stdout


def test_step_and_return_map_refuse_parameters_out_of_range(drop):
    """The Python API refuses what the command line refuses: concrete parameters out of range are a
    ValueError naming the field, from jaxfoam.step and jaxfoam.return_map; under jit they pass untested
    (no values), and a valid call still runs."""
    model, s0 = drop
    with pytest.raises(ValueError, match="Params.eta must be >= 0 Pa s\\^m, got -1.0"):
        jf.step(model, s0, PARAMS.replace(eta=-1.0))
    bbar = jnp.eye(3)[None]
    f = jnp.eye(2)[None] * 1.01
    with pytest.raises(ValueError, match=r"Params.m must be in \(0, 5\], got 0.0"):
        jf.return_map(bbar, f, PARAMS.replace(m=0.0), 1e-3)
    b, s = jf.return_map(bbar, f, PARAMS, 1e-3)
    assert np.isfinite(np.asarray(b)).all() and float(s[0]) >= 0.0
