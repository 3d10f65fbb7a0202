"""The compiled-program guard (`jaxfoam._compile_guard`): a process that compiles many programs frees
them before it exceeds Linux's per-process limit on memory mappings (vm.max_map_count).

Contract: the guard clears JAX's caches exactly when the mapping count exceeds MAP_FRACTION of the
limit, and does nothing when the counts are unknown; clearing releases the mappings that compiled
programs hold (measured here on real compilations), and a program used again afterwards still gives
the same result."""
import os

import jax
import numpy as np
import pytest

from jaxfoam import _compile_guard as G


def test_threshold_and_unknown_counts(monkeypatch):
    calls = []
    monkeypatch.setattr(jax, "clear_caches", lambda: calls.append(1))
    assert G.MAP_FRACTION == 0.5
    assert G.release_if_near_map_limit(count=1000, limit=65530) is False
    assert G.release_if_near_map_limit(count=32765, limit=65530) is False   # exactly half: kept
    assert calls == []
    assert G.release_if_near_map_limit(count=32766, limit=65530) is True
    assert calls == [1]
    # no /proc (another OS): nothing happens
    monkeypatch.setattr(G, "_map_count", lambda: None)
    assert G.release_if_near_map_limit() is False
    assert calls == [1]


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="needs Linux /proc")
def test_clearing_releases_compiled_programs_mappings():
    """Rollouts compiled on three grids add mappings (hundreds each) that a forced release gives back
    (to within 20% of what they added); a rollout compiled before the release gives the same positions
    after it."""
    import jaxfoam as jf

    scene = jf.load_scene(os.path.join(os.path.dirname(__file__), "..", "..", "experiments", "scenes", "drop_2d.json"))
    params = jf.Params(mu=200.0, kappa=scene.kappa, sigma_y=20.0, eta=5.0, m=0.5, rho=scene.density)
    sims = [jf.Simulator(scene, [0.002], params, dx=dx, substeps=2) for dx in (0.04, 0.041, 0.042)]
    first = np.asarray(sims[0].rollout(params)[0].x)
    start = G._map_count()
    for sim in sims[1:]:
        jax.block_until_ready(sim.rollout(params)[0].x)
        jax.block_until_ready(sim.rollout(params, adjoint=jf.Autodiff())[0].x)
    grown = G._map_count()
    assert grown - start > 100, (start, grown)
    assert G.release_if_near_map_limit(count=2, limit=2) is True
    after = G._map_count()
    assert after - start <= 0.2 * (grown - start), (start, grown, after)
    np.testing.assert_array_equal(np.asarray(sims[0].rollout(params)[0].x), first)
