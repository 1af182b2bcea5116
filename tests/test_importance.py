"""Importance sampling from a Laplace approximation against closed forms: it must recover the posterior where the
approximation is off, and refuse to vouch for an answer where the approximation misses the posterior."""

import numpy as np
import pytest
from scipy import stats

from newdyn import importance

SETTINGS = importance.ISSettings(seed=3, batch=1000, max_draws=8000)


def gaussian(mean, cov):
    """Log-likelihood of a correlated Gaussian posterior (flat prior on a wide box), batched."""
    precision = np.linalg.inv(cov)

    def log_likelihood(theta):
        d = theta - mean
        return -0.5 * np.einsum("ni,ij,nj->n", d, precision, d)

    return log_likelihood


def box(low, high):
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    return lambda theta: np.where(np.all((theta >= low) & (theta <= high), axis=1), 0.0, -np.inf)


def moments(idata, names):
    draws = np.column_stack([idata.posterior[n].values.ravel() for n in names])
    return draws.mean(axis=0), np.cov(draws.T)


def test_a_correlated_gaussian_is_recovered_from_an_approximation_that_is_off_centre_and_too_narrow():
    mean = np.array([3.0e6, 0.35])  # scales as far apart as a stiffness and a crack depth
    sd = np.array([8.0e3, 1.0e-3])
    cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * np.outer(sd, sd)
    approx_mean = mean + np.array([0.3, -0.3]) * sd  # off along the ridge, as a least-squares stop short of the optimum is
    approx_cov = 0.8**2 * cov
    idata = importance.sample(gaussian(mean, cov), box([0, 0], [1e7, 1]), ["k", "a"], approx_mean, approx_cov, SETTINGS)
    got_mean, got_cov = moments(idata, ["k", "a"])
    assert idata.attrs["converged"] == 1 and idata.attrs["pareto_k"] <= 0.7
    ess = idata.attrs["ess_bulk"]
    assert ess >= SETTINGS.ess_min
    # within 4 Monte Carlo standard errors of the exact moments
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(ess))
    np.testing.assert_allclose(np.sqrt(np.diag(got_cov)), sd, rtol=4 / np.sqrt(2 * ess))
    assert got_cov[0, 1] / np.sqrt(got_cov[0, 0] * got_cov[1, 1]) == pytest.approx(-0.9, abs=0.03)


def test_a_posterior_cut_by_its_prior_bound_has_the_truncated_normals_mean():
    """A fault's severity piled against zero: N(0.001, 0.002²) truncated to [0, 1], the approximation at the bound."""
    mu, sigma = 0.001, 0.002
    idata = importance.sample(lambda t: -0.5 * ((t[:, 0] - mu) / sigma) ** 2, box([0], [1]), ["alpha"], np.array([0.0]),
                              np.array([[sigma**2]]), SETTINGS)
    exact = stats.truncnorm((0 - mu) / sigma, (1 - mu) / sigma, loc=mu, scale=sigma)
    got = idata.posterior["alpha"].values.ravel()
    assert idata.attrs["converged"] == 1
    assert got.min() >= 0
    assert got.mean() == pytest.approx(exact.mean(), abs=4 * exact.std() / np.sqrt(idata.attrs["ess_bulk"]))
    assert idata.attrs["n_proposals"] > len(idata.importance["alpha"])  # draws below the bound cost no likelihood


def test_a_posterior_with_a_second_mode_in_the_approximations_tail_is_not_verified():
    """As much mass again 5 sds from where the approximation sits, within the proposal's reach but far in its
    tail: the few draws there carry huge weights, and k̂ says the estimate cannot be trusted."""

    def two_modes(theta):
        x = theta[:, 0]
        return np.logaddexp(-0.5 * x**2, -0.5 * ((x - 5.0) / 0.5) ** 2 - np.log(0.5))

    idata = importance.sample(two_modes, box([-100], [100]), ["x"], np.array([0.0]), np.array([[1.0]]), SETTINGS)
    assert idata.attrs["converged"] == 0 and idata.attrs["pareto_k"] > 0.7
    assert "misses the posterior" in idata.attrs["reason"]


def test_a_proposal_far_too_narrow_is_caught_by_pareto_k():
    """The approximation 20 times too narrow: the weights' tail is heavy, k̂ > 0.7, unverified."""
    idata = importance.sample(lambda t: -0.5 * t[:, 0] ** 2, box([-100], [100]), ["x"], np.array([0.0]), np.array([[0.05**2]]),
                              importance.ISSettings(seed=2, batch=1000, max_draws=2000, df=100.0))
    assert idata.attrs["pareto_k"] > 0.7 and idata.attrs["converged"] == 0


def test_the_same_seed_gives_the_same_draws():
    run = [importance.sample(gaussian(np.zeros(2), np.eye(2)), box([-9, -9], [9, 9]), ["a", "b"], np.zeros(2), np.eye(2), SETTINGS)
           for _ in range(2)]
    np.testing.assert_array_equal(run[0].posterior["a"].values, run[1].posterior["a"].values)
