"""The fitter with particle resampling and fracture switched on (FitSettings.resample / .fracture).

Contracts checked:
- the gradient of the fit's loss L(z) = 0.5 |r(z)|^2 that the fitter uses (J^T r, J by forward mode
  through the rollout with resampling and fracture) equals central finite differences of L in float64,
  at a point and step where no resampling or fracture decision flips (checked, not assumed: the
  decisions of every pass and every substep are recorded at z and at z +- h and must be identical);
- both features actually act in that case (points are inserted or merged, points are weak), so the
  comparison covers their derivatives;
- a tiny fit with both on runs end to end (loss, Jacobian, discretization check, fit.json settings)
  and returns finite parameters; bad settings give errors that name the field.

Why the tolerance holds: with the decisions fixed the rollout is a smooth function of z except at the
kinks of floor contact and of the yield condition, and the forward-mode Jacobian is the exact
derivative of the discrete rollout. Central differences in float64 with step h = 1e-5 (in log
coordinates, a 1e-5 relative parameter change) carry a truncation error ~h^2 |L'''| / 6 ~ 1e-10
relative and a round-off error ~eps |L| / h ~ 1e-11 relative; a kink crossed inside +-h is the only
larger source (grad_horizon measured up to 3.7e-4 after contact on the drop). The bound 1e-5 is
far below what a missing or wrong derivative term gives (dropping the strain release of weak points,
or the transfers of inserted points, changes the gradient at the percent level or more; a decision
flip inside +-h gives an error of order jump / h, i.e. > 1).
"""
import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting.check
import fitting.cli
import fitting.settings
from fitting import CalibrationError, FitSettings, build_problem, calibrate
from fitting.cli import add_fit_parser, parse_feature, settings_from_args
from jaxfoam.fracture import FractureConfig, release, weak_points
from jaxfoam.resample import ResampleConfig
from fitting import synthesize

from helpers import central_difference, scene as zoo_scene

# A 8 x 6 cm block slumping on a floor, 2 cm grid (tiny: ~50 particles at 4 per cell, 3 frames).
SLUMP = zoo_scene("slump")
TRUTH = {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}
FIT_DX = 0.02
# Aggressive but valid settings, so that both stages act on a tiny coarse block: resampling every 3
# substeps refilling any cell with fewer than ppc points; fracture marking points whose neighbourhood
# density ratio is below 0.45 (box corners sit near 0.28, flat surfaces near 0.6).
RESAMPLE = ResampleConfig(every=3, sparse_fraction=1.0)
FRACTURE = FractureConfig(density_ratio=0.45)
FD_STEP = 1e-5
GRAD_RTOL = 1e-5

# Decision records, filled by host callbacks during a rollout: (kind, summary) in execution order.
_RECORD = []


def _note(kind):
    def cb(*vals):
        _RECORD.append((kind,) + tuple(np.asarray(v).item() for v in vals))
    return cb


class RecordingResample(ResampleConfig):
    """ResampleConfig whose passes report their outcome (active count, sum of active positions) to
    the host: two rollouts with equal records made the same insert / merge decisions."""

    def apply(self, state, grid, index, hold=None):
        out = super().apply(state, grid, index, hold)
        x = jax.lax.stop_gradient(out.x)
        jax.debug.callback(_note("resample"), jnp.sum(out.active), jnp.sum(jnp.where(out.active[:, None], x, 0.0)))
        return out


class RecordingFracture(FractureConfig):
    """FractureConfig whose substeps report how many points are weak and their total mass."""

    def apply(self, new, old, grid_m, grid):
        weak = weak_points(old, grid_m, grid, self.threshold(old.dim))
        jax.debug.callback(_note("fracture"), jnp.sum(weak), jnp.sum(jnp.where(weak, old.mass, 0.0)))
        return release(new, weak)


def _first_difference(a, b):
    """None if the two decision records agree, else a description of the first difference. Counts must
    be equal; the position / mass sums move by O(h) continuously (measured ~1e-7 relative for h = 1e-5),
    a flip moves them by at least an insertion radius or a particle's mass (> 1e-3 relative here)."""
    if len(a) != len(b):
        return f"{len(a)} against {len(b)} records"
    for k, (ra, rb) in enumerate(zip(a, b)):
        if ra[0] != rb[0] or ra[1] != rb[1] or not np.isclose(ra[2], rb[2], rtol=1e-4, atol=0.0):
            return f"record {k}: {ra} against {rb}"
    return None


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit_features")
    silh = synthesize(SLUMP, TRUTH, dx=0.01, frames=4, duration=0.15, noise=0.0, seed=1)
    path = d / "slump.h5"
    silh.write(path)
    return silh, path


# The gradient test and the end-to-end fit share these settings, so the fit reuses the compiled rollouts.
def _settings(**kw):
    return FitSettings(dx=FIT_DX, fixed={"eta": 5.0, "m": 0.6}, starts=1,
                       resample=RecordingResample(every=3, sparse_fraction=1.0),
                       fracture=RecordingFracture(density_ratio=0.45), **kw)


@pytest.mark.slow
def test_loss_gradient_with_resampling_and_fracture_matches_central_differences(data):
    silh, _ = data
    problem = build_problem(silh, _settings())
    assert problem.sim.resample is not None and problem.sim.fracture is not None
    assert problem.sim.resample.ppc == 4  # the resampler's target is the fit's ppc
    n0 = int(np.sum(problem.sim.state0.active))
    assert problem.sim.state0.capacity == 2 * n0  # room for inserted points (capacity_factor 2)
    z = np.asarray(problem.transform.to_unconstrained(np.array([120.0, 30.0])))

    # The loss and its finite differences come from the same compiled function the optimizer calls
    # (residual_and_jacobian: its r is the plain rollout's residual), so the test compiles one rollout.
    def loss_at(zz):
        _RECORD.clear()
        r, J = problem.residual_and_jacobian(zz)
        r = np.asarray(r)
        # Sorted: the Jacobian's column groups run in concurrent threads (the tuning's jacobian_threads), so
        # their records interleave in any order; a flipped decision still changes the multiset.
        return 0.5 * float(r @ r), np.asarray(J).T @ r, sorted(_RECORD)

    loss0, grad, at_z = loss_at(z)
    passes = [rec for rec in at_z if rec[0] == "resample"]
    subs = [rec for rec in at_z if rec[0] == "fracture"]
    cols = len(z)  # the callbacks fire once per Jacobian column (one jvp rollout each)
    assert len(subs) == cols * problem.sim.total_substeps and len(passes) == cols * (problem.sim.total_substeps // 3)
    # Both stages act: the active count changed (insertions / merges) and points were weak.
    assert any(rec[1] != n0 for rec in passes), "resampling never changed the particle set"
    assert sum(rec[1] for rec in subs) > 0, "no point was ever weak"

    def loss_along(zz, name):
        loss, _, rec = loss_at(zz)
        flip = _first_difference(rec, at_z)
        assert flip is None, f"a decision flipped within +-h along {name}: {flip}"
        return loss

    fd = np.zeros_like(grad)
    for i, name in enumerate(problem.transform.names):
        fd[i] = central_difference(lambda zz: loss_along(zz, name), z, np.eye(len(z))[i], h=FD_STEP)
    assert loss0 > 0 and np.all(np.abs(grad) > 1e-8 * loss0)  # a derivative that is really there
    np.testing.assert_allclose(grad, fd, rtol=GRAD_RTOL, atol=0.0)


@pytest.mark.slow
def test_tiny_fit_with_resampling_and_fracture_runs_end_to_end(data, monkeypatch):
    """A fit with both on: finite fitted parameters, a loss no higher than at the start, the configs as
    the rollouts used them in the settings. (The fit reuses the gradient test's compiled Jacobian; its
    discretization check, which compiles two more rollouts, is checked separately below.)"""
    silh, _ = data
    res = calibrate(silh, _settings(max_iter=2, dx_check=False,
                                    start_ranges={"mu": (119.0, 121.0), "sigma_y": (29.0, 31.0)}))
    _RECORD.clear()
    assert all(np.isfinite(res.params[n]) for n in ("mu", "sigma_y"))
    assert 5.0 <= res.params["mu"] <= 2000.0 and 0.5 <= res.params["sigma_y"] <= 500.0
    assert np.isfinite(res.loss) and res.loss <= res.loss_history[0] and res.iterations >= 1
    assert all(np.isfinite(v) for v in res.stderr.values())
    s = json.loads(json.dumps(res.to_dict()))["settings"]
    assert s["resample"]["every"] == 3 and s["resample"]["sparse_fraction"] == 1.0 and s["resample"]["ppc"] == 4
    assert s["fracture"] == {"density_ratio": 0.45, "neck_thickness": None}
    plain = build_problem(silh, FitSettings(dx=FIT_DX, fixed={"eta": 5.0, "m": 0.6}))
    assert plain.sim.resample is None and plain.sim.state0.capacity == int(np.sum(plain.sim.state0.active))
    assert s["capacity"] == 2 * plain.sim.state0.capacity  # capacity_factor 2: slots for inserted points

    # The discretization check builds its finer problem with the same features.
    seen = []

    class Stop(Exception):
        pass

    def spy(data, settings):
        p = build_problem(data, settings)
        seen.append((p.dx, p.sim.resample, p.sim.fracture))
        raise Stop

    monkeypatch.setattr(fitting.check, "build_problem", spy)  # the discretization check builds its problem there
    problem = build_problem(silh, _settings())
    with pytest.raises(Stop):
        fitting.check.discretization_error(problem, np.zeros(2), np.zeros((1, 2)))
    (dx, rs, fr), = seen
    assert dx == pytest.approx(FIT_DX * fitting.settings.DX_CHECK_RATIO)
    assert rs == problem.sim.resample and fr == problem.sim.fracture and rs is not None and fr is not None


def test_fit_command_line_flags_reach_the_settings():
    """`jaxfoam fit --resample [fields] --fracture [fields]`: alone the configs' defaults; absent, off."""
    ap = argparse.ArgumentParser().add_subparsers()
    parser = add_fit_parser(ap)
    base = ["data.h5", "--out", "fit.json"]
    off = settings_from_args(parser.parse_args(base))
    assert off.resample is None and off.fracture is None
    on = settings_from_args(parser.parse_args(base + ["--resample", "--fracture"]))
    assert on.resample == ResampleConfig() and on.fracture == FractureConfig()
    some = settings_from_args(parser.parse_args(base + ["--resample", "every=10,sparse_fraction=0.4",
                                                        "--fracture", "density_ratio=0.15"]))
    assert some.resample == ResampleConfig(every=10, sparse_fraction=0.4)
    assert some.fracture == FractureConfig(density_ratio=0.15)
    assert some.to_dict()["resample"]["every"] == 10 and some.to_dict()["fracture"] == {"density_ratio": 0.15, "neck_thickness": None}
    with pytest.raises(CalibrationError, match="fracture: FractureConfig.density_ratio must be in"):
        settings_from_args(parser.parse_args(base + ["--fracture", "density_ratio=2"]))


def test_feature_settings_parse_and_bad_settings_name_the_field():
    assert FitSettings().resample is None and FitSettings().fracture is None
    assert FitSettings(resample=True, fracture=True).resample == ResampleConfig()
    assert FitSettings(resample={"every": 5}).resample == ResampleConfig(every=5)
    assert FitSettings(resample=False).resample is None
    assert parse_feature("", ResampleConfig, "resample") == ResampleConfig()
    assert parse_feature("every=10,ppc=none", ResampleConfig, "resample") == ResampleConfig(every=10)
    assert parse_feature("density_ratio=0.15", FractureConfig, "fracture") == FractureConfig(density_ratio=0.15)
    assert parse_feature(None, FractureConfig, "fracture") is None
    with pytest.raises(CalibrationError, match="--resample: unknown field 'evry'"):
        parse_feature("evry=3", ResampleConfig, "resample")
    with pytest.raises(CalibrationError, match="--resample: every must be a int"):
        parse_feature("every=2.5", ResampleConfig, "resample")
    with pytest.raises(CalibrationError, match="resample: unknown field"):
        FitSettings(resample={"often": 3})
    with pytest.raises(CalibrationError, match="resample must be None, True/False"):
        FitSettings(resample="yes")
    with pytest.raises(CalibrationError, match="resample: ResampleConfig.every must be an integer >= 1"):
        FitSettings(resample=ResampleConfig(every=0)).validate()
    with pytest.raises(CalibrationError, match="fracture: FractureConfig.density_ratio must be in"):
        FitSettings(fracture=FractureConfig(density_ratio=1.5)).validate()


def test_resampling_needs_a_square_ppc(data):
    """The resampler refills to a k^d lattice: a fit at 5 particles per cell with the default target is
    refused before any rollout, naming the fix."""
    silh, _ = data
    with pytest.raises(CalibrationError, match="resample: the fit's ppc = 5 is not k"):
        build_problem(silh, FitSettings(dx=FIT_DX, ppc=5, resample=True))
    # an explicit target is accepted
    problem = build_problem(silh, FitSettings(dx=FIT_DX, ppc=5, resample=ResampleConfig(ppc=4)))
    assert problem.sim.resample.ppc == 4


def test_feature_defaults_agree_with_model_choice():
    """MODEL_CHOICE.md's defaults block states resampling and fracture off for fits (as comment lines,
    outside the keys tests/test_model_choice.py parses), and the fitter's constants and CLI agree."""
    import argparse
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "experiments" / "MODEL_CHOICE.md").read_text()
    block = re.findall(r"```defaults\n(.*?)```", text, flags=re.S)[0]
    assert re.search(r"^# resample = off\b", block, flags=re.M) and re.search(r"^# fracture = off\b", block, flags=re.M)
    assert fitting.settings.FIT_RESAMPLE is None and fitting.settings.FIT_FRACTURE is None
    assert FitSettings().resample is None and FitSettings().fracture is None
    ap = fitting.cli.add_fit_parser(argparse.ArgumentParser().add_subparsers())
    assert ap.get_default("resample") is None and ap.get_default("fracture") is None
