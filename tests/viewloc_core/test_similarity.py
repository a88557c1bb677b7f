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
    # Point-to-line with random normals constrains all four parameters too.
    ang = rng.uniform(0, np.pi, 40)
    normals = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    got2 = sim2.fit_point_to_line(src, dst, normals)
    assert got2 is not None
    np.testing.assert_allclose(sim2.apply(got2, src), dst, atol=1e-5)


def test_point_to_line_degenerate_on_one_line():
    src = np.stack([np.linspace(0, 10, 20), np.zeros(20)], axis=1)
    normals = np.tile([0.0, 1.0], (20, 1))
    assert sim2.fit_point_to_line(src, src, normals) is None
