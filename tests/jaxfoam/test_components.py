"""The rollout's working form (jaxfoam._xla_cpu.layout.to_components): what it keeps, and that it loses nothing."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfoam import make_state
from jaxfoam._xla_cpu.layout import from_components, to_components


def _random_state(d, n=7, seed=0):
    rng = np.random.default_rng(seed)
    st = make_state(rng.random((n, d)), np.full(n, 1e-4), np.full(n, 8e-3))
    A = rng.normal(size=(n, 3, 3))
    if d == 2:
        A[:, :2, 2] = A[:, 2, :2] = 0.0  # plane strain: no xz, yz
    b = A @ np.swapaxes(A, 1, 2) + np.eye(3)  # symmetric positive definite
    b /= np.cbrt(np.linalg.det(b))[:, None, None]
    return st.replace(bbar_e=jnp.asarray(b), F=jnp.asarray(rng.normal(size=(n, d, d))),
                      C=jnp.asarray(rng.normal(size=(n, d, d))))


@pytest.mark.slow
@pytest.mark.parametrize("d, kept", [(2, 4), (3, 6)])
def test_component_form_keeps_the_independent_components_of_bbar_and_round_trips_exactly(d, kept):
    """bbar_e is symmetric (and in plane strain has no xz, yz): the working form keeps 4 (2D) or 6 (3D)
    arrays of it, and converting back restores every entry bit for bit."""
    st = _random_state(d)
    comp = to_components(st)
    assert len(comp.bbar_e) == kept and all(np.shape(c) == (7,) for c in comp.bbar_e)
    back = from_components(comp)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(st)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
