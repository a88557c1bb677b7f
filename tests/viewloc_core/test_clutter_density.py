"""Clutter attribute density estimated from the image's own features."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.clutter_density import PRIOR_PSEUDO_FEATURES, log_image_density


def test_a_lone_feature_keeps_the_prior():
    log_prior = np.array([-1.7])
    out = log_image_density(np.array([[0.3, 0.1]]), np.array([0.1, 0.5]), log_prior)
    np.testing.assert_allclose(out, log_prior)


def test_a_feature_is_left_out_of_its_own_estimate():
    # Two features 40 standard deviations apart see nothing of each other:
    # only the prior's share of the mixture is left.
    attrs = np.array([[0.0], [4.0]])
    log_prior = np.log(np.array([0.2, 0.3]))
    out = log_image_density(attrs, np.array([0.1]), log_prior)
    expected = log_prior + np.log(PRIOR_PSEUDO_FEATURES / (1.0 + PRIOR_PSEUDO_FEATURES))
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_repeated_attributes_are_common_and_a_distinct_one_is_rare():
    # A checkerboard: 500 right-angle junctions, and one junction of 50°.
    rng = np.random.default_rng(0)
    common = np.column_stack([np.full(500, np.pi / 2), np.zeros(500)])
    common += rng.normal(0.0, 0.01, common.shape)
    attrs = np.vstack([common, [[np.radians(50.0), 0.0]]])
    log_prior = np.full(len(attrs), np.log(1.0 / (np.pi * 0.7 * 2.5)))
    out = log_image_density(attrs, np.array([0.12, 0.7]), log_prior)
    assert np.all(out[:500] > log_prior[:500] + 2.0)
    assert out[500] < log_prior[500]


def test_the_estimate_is_a_density_of_the_attributes_unit():
    # 20,000 draws of N(0, 1): the kernel density (unit kernel) at 0 is that
    # of N(0, 2), 1/sqrt(4π); measured in an attribute unit 3 times finer, the
    # density is a third.
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 1.0, (20000, 1))
    at_zero = np.argmin(np.abs(z[:, 0]))
    tiny_prior = np.full(len(z), -50.0)
    out = log_image_density(z, np.array([1.0]), tiny_prior)
    np.testing.assert_allclose(np.exp(out[at_zero]), 1.0 / np.sqrt(4 * np.pi), rtol=0.05)
    out3 = log_image_density(3.0 * z, np.array([3.0]), tiny_prior)
    np.testing.assert_allclose(out3, out - np.log(3.0), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 60), st.integers(0, 2**31 - 1))
def test_the_order_of_the_features_does_not_matter(n, seed):
    rng = np.random.default_rng(seed)
    attrs = rng.normal(0.0, 0.5, (n, 2))
    log_prior = rng.normal(-1.0, 0.3, n)
    sd = np.array([0.12, 0.7])
    out = log_image_density(attrs, sd, log_prior)
    perm = rng.permutation(n)
    np.testing.assert_allclose(log_image_density(attrs[perm], sd, log_prior[perm]), out[perm],
                               atol=1e-9)
    # Never below the prior's share of the mixture.
    assert np.all(out >= log_prior + np.log(PRIOR_PSEUDO_FEATURES / (n - 1 + PRIOR_PSEUDO_FEATURES))
                  - 1e-9)


def test_an_undefined_attribute_keeps_the_prior_and_is_no_ones_neighbour():
    attrs = np.array([[0.0], [np.nan], [0.0], [np.inf]])
    log_prior = np.full(4, -1.0)
    out = log_image_density(attrs, np.array([0.5]), log_prior)
    np.testing.assert_allclose(out[[1, 3]], log_prior[[1, 3]])
    np.testing.assert_allclose(out[[0, 2]], log_image_density(attrs[[0, 2]], np.array([0.5]),
                                                              log_prior[[0, 2]]))
