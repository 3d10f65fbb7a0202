"""Fracture (jaxfoam.fracture): a weak single-file chain between two blocks stops carrying tension,
so the pull on a plate drops to zero and a block hanging from the chain falls freely; intact material
(corners included) is never weak."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfoam
from jaxfoam.fracture import FractureConfig, collider_force, density_ratio

DX = 0.0025          # grid spacing, m
DT = 2e-5            # substep, s (CFL: c = 3.9 m/s, 0.3 dx / c = 1.9e-4 s)
STEPS = 300
G = 9.81
STRETCH = 1.3        # elastic pre-stretch of the chain along y (isochoric bbar_e)
PARAMS = jaxfoam.Params(mu=1000.0, kappa=3000.0, sigma_y=1e4, eta=0.0, m=1.0, rho=100.0)  # elastic


def _geometry():
    """Top block (held by the top plate), bottom block, and a single file of points 0.8 dx apart
    between them (density ratio 0.18 < 0.2: weak; the blocks' points are >= 0.39)."""
    k = DX / 2
    xs = np.arange(-0.005 + k / 2, 0.005, k)
    top = np.array([[a, b] for a in xs for b in np.arange(0.06 + k / 2, 0.075, k)])
    bot = np.array([[a, b] for a in xs for b in np.arange(0.03 + k / 2, 0.04, k)])
    ys = np.arange(0.04 + 0.4 * DX, 0.06 - 0.2 * DX, 0.8 * DX)
    chain = np.stack([np.full_like(ys, 0.25 * k), ys], 1)
    x = np.concatenate([top, bot, chain])
    vol = np.full(len(x), k * k)
    st = jaxfoam.make_state(x, vol, PARAMS.rho * vol)
    in_chain = np.arange(len(x)) >= len(top) + len(bot)
    # Pre-stretch the chain's points except the two at each end (those touch the blocks, are not
    # weak, and would keep their stretch): plain MPM carries this tension into the blocks.
    stretched = in_chain & (np.arange(len(x)) >= len(top) + len(bot) + 2) & (np.arange(len(x)) < len(x) - 2)
    b = jnp.diag(jnp.asarray([1 / STRETCH, STRETCH ** 2, 1 / STRETCH]))
    st = st.replace(bbar_e=jnp.where(jnp.asarray(stretched)[:, None, None], b[None], st.bbar_e))
    bottom = (np.arange(len(x)) >= len(top)) & ~in_chain
    return st, jnp.asarray(bottom)


def _scenes():
    """Pull: gravity off, both blocks held by still plates, the chain pre-stretched between them.
    Fall: gravity on, both plates still, the bottom plate moved far below (the block hangs free)."""
    pull = jaxfoam.load_scene(dict(
        kind="squeeze", dim=2, gravity=[0.0, 0.0], density=100.0, kappa=3000.0,
        domain=dict(min=[-0.03, -0.02], max=[0.03, 0.10]),
        plates=[dict(center=[0, 0.0725], half_size=[0.01, 0.0035],
                     motion=dict(type="samples", times=[0, 1], positions=[[0, 0.0725], [0, 0.0725]])),
                dict(center=[0, 0.035], half_size=[0.01, 0.0055])],
        initial_shape=dict(type="box", min=[-0.005, 0.03], max=[0.005, 0.07])))
    top, bottom = pull.plates
    fall = dataclasses.replace(
        pull, gravity=jnp.asarray([0.0, -G]),
        plates=(top, dataclasses.replace(bottom, center=jnp.asarray([0.0, -0.5]))))
    return pull, fall


def _run(fracture):
    st, bottom = _geometry()
    pull, _ = _scenes()
    grid = jaxfoam.make_grid(pull, DX)

    @jax.jit
    def run(s, scene):
        model = jaxfoam.Model(scene=scene, dt=DT, grid=grid, fracture=fracture)

        def body(s, _):
            f = collider_force(s, PARAMS, scene, grid, DT, region=lambda nx: nx[:, 1] > 0.065)
            mb = jnp.where(bottom, s.mass, 0.0)
            com = jnp.sum(mb[:, None] * s.x, 0) / jnp.sum(mb)
            return jaxfoam.step(model, s, PARAMS), (f[1], com[1])
        return jax.lax.scan(body, s, None, length=STEPS)

    return st, grid, run


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name, frac in (("plain", None), ("fracture", FractureConfig())):
        st, grid, run = _run(frac)
        pull, fall = _scenes()
        out[name] = dict(pull=jax.device_get(run(st, pull)[1][0]), fall=jax.device_get(run(st, fall)[1][1]))
    return out


@pytest.mark.slow
def test_fracture_releases_tension(runs):
    """The force the top plate exerts on the foam balances the chain's tension: it builds up to
    > 0.5 N/m (upward) in plain MPM; with fracture the weak chain carries no tension and the force
    never exceeds 3% of plain MPM's peak."""
    plain = np.asarray(runs["plain"]["pull"])
    frac = np.asarray(runs["fracture"]["pull"])
    assert plain.max() > 0.5 and plain[STEPS // 2:].mean() > 0.3, plain[::30]  # N/m
    assert np.abs(frac).max() < 0.03 * plain.max(), (np.abs(frac).max(), plain.max())


@pytest.mark.slow
def test_separated_piece_falls_freely(runs):
    """Free fall: with fracture the bottom block's centre of mass accelerates at -g within 2%;
    in plain MPM the stretched chain holds it back (acceleration above -g/2)."""
    t = DT * np.arange(STEPS)
    sl = slice(STEPS // 5, None)
    acc = {k: 2.0 * np.polyfit(t[sl], runs[k]["fall"][sl], 2)[0] for k in runs}
    assert abs(acc["fracture"] + G) < 0.02 * G, acc
    assert acc["plain"] > -0.5 * G, acc


@pytest.mark.slow
def test_intact_material_is_never_weak():
    """A jittered block (corners included) in 2D and 3D stays above the default thresholds; the
    single file of points 0.8 dx apart is below it."""
    for dim in (2, 3):
        scene = jaxfoam.load_scene(dict(kind="drop", dim=dim, density=100.0, kappa=1000.0,
                                        domain=dict(min=[0.0] * dim, max=[1.0] * dim),
                                        initial_shape=dict(type="box", min=[0.3] * dim, max=[0.6] * dim)))
        dx = 1.0 / 16
        grid = jaxfoam.make_grid(scene, dx)
        st = jaxfoam.init_state(scene, dx, rho=100.0)
        r = np.asarray(jax.jit(lambda s: density_ratio(s, jaxfoam.p2g(s, PARAMS, grid, 1e-4)[1], grid))(st))
        assert r.min() > FractureConfig().threshold(dim) * 1.02, (dim, r.min())
    st, _ = _geometry()
    grid = jaxfoam.make_grid(_scenes()[0], DX)
    r = np.asarray(jax.jit(lambda s: density_ratio(s, jaxfoam.p2g(s, PARAMS, grid, DT)[1], grid))(st))
    stretched = np.asarray(st.bbar_e[:, 1, 1]) > 1.5
    assert np.all(r[stretched] < FractureConfig().threshold(2))


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="density_ratio"):
        FractureConfig(density_ratio=1.5).validate(2)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["shaving_cream_3d", "pie_throw", "smore"])
def test_showcase_scene_loads_and_runs_finite(name):
    """Every showcase file parses (scene, parameters, SDF colliders, resampling and fracture
    settings) and 3 substeps at twice its preview dx (with its colliders and fracture) stay finite."""
    import importlib.util
    from pathlib import Path
    root = Path(__file__).resolve().parents[2] / "experiments" / "showcase"
    spec = importlib.util.spec_from_file_location("showcase", root / "showcase.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    show = mod.load_showcase(root / f"{name}.json")
    assert show["colliders"] or show["scene"].plates
    coarse = dict(show["cpu"], dx=2 * show["cpu"]["dx"], dtype="float64")
    sim = mod.make_simulator(show, coarse, frame_times=[1e-3])
    step = jax.jit(sim.step)
    s = sim.state0
    for _ in range(3):
        s = step(s, show["params"].astype(jnp.float64))
    act = np.asarray(s.active)
    assert act.sum() > 50
    for field in ("x", "v", "F", "bbar_e"):
        assert np.all(np.isfinite(np.asarray(getattr(s, field))[act])), field
    assert float(s.t) > 0
