"""2D similarity algebra and fits (property-based)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from viewloc_core import similarity as sim2

sims = st.tuples(
    st.floats(-300, 300), st.floats(-300, 300), st.floats(-3.1, 3.1), st.floats(0.2, 5.0)
).map(np.array)


@given(sims, sims)
def test_compose_matches_sequential_application(a, b):
    pts = np.array([[1.0, 2.0], [-30.0, 7.0], [12.0, -4.0]])
    np.testing.assert_allclose(
        sim2.apply(sim2.compose(a, b), pts), sim2.apply(a, sim2.apply(b, pts)), atol=1e-6
    )


@given(sims)
def test_inverse(a):
    pts = np.array([[5.0, -3.0], [40.0, 22.0]])
    np.testing.assert_allclose(sim2.apply(sim2.inverse(a), sim2.apply(a, pts)), pts, atol=1e-6)


@given(sims)
def test_point_fits_recover_the_transform(a):
    rng = np.random.default_rng(0)
    src = rng.uniform(-60, 60, (40, 2))
    dst = sim2.apply(a, src)
    got = sim2.fit_points(src, dst)
    assert got is not None
    np.testing.assert_allclose(sim2.apply(got, src), dst, atol=1e-6)
