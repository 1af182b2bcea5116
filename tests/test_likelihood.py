"""Gaussian likelihood and grid posteriors against closed forms."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from newdyn import likelihood
from newdyn.likelihood import gaussian_log_prior, grid_posterior, log_likelihood, reduced_chi2

# z such that N(0, 1) puts 0.94 between −z and z; a Gaussian's 94 % HDI is mean ± z sd.
Z_94 = stats.norm.ppf(0.97)


def test_log_likelihood_is_the_sum_of_gaussian_log_densities():
    rng = np.random.default_rng(0)
    sigma = np.array([0.5, 2.0, 1e-3])
    data = rng.normal(size=(3, 50))
    models = data + rng.normal(size=(4, 3, 50)) * sigma[:, None]  # four grid points

    expected = stats.norm.logpdf(data, loc=models, scale=sigma[:, None]).sum(axis=-1)
    np.testing.assert_allclose(log_likelihood(data, models, sigma, per_channel=True), expected, rtol=1e-12)
    np.testing.assert_allclose(log_likelihood(data, models, sigma), expected.sum(axis=-1), rtol=1e-12)
    assert np.ndim(log_likelihood(data, models[0], sigma)) == 0


def test_a_large_batch_scores_each_model_as_it_would_alone():
    """A batch scored a few rows at a time gives every row the same bits as scored alone, and as the broadcast of
    one σ per model does."""
    rng = np.random.default_rng(1)
    sigma = np.array([0.5, 2.0, 1e-3])
    data = rng.normal(size=(3, 40))
    models = data + rng.normal(size=(2 * likelihood.SCORED_ROWS + 3, 3, 40)) * sigma[:, None]

    alone = np.array([log_likelihood(data, m, sigma, per_channel=True) for m in models])
    assert np.array_equal(log_likelihood(data, models, sigma, per_channel=True), alone)
    assert np.array_equal(log_likelihood(data, models, np.tile(sigma, (len(models), 1)), per_channel=True), alone)


def test_log_likelihood_refuses_mismatched_shapes_and_bad_sigma():
    data = np.zeros((2, 10))
    with pytest.raises(ValueError, match="model"):
        log_likelihood(data, np.zeros((5, 2, 9)), [1.0, 1.0])
    with pytest.raises(ValueError, match="sigma"):
        log_likelihood(data, data, [1.0, 0.0])
    with pytest.raises(ValueError, match="sigma"):
        log_likelihood(data, data, [1.0])


@pytest.fixture(scope="module")
def linear_gaussian():
    """m(φ) = φ·x observed with Gaussian noise, Gaussian prior: a posterior known in closed form.

    Scales follow the paper's base case: kT1 on 2.0e6..4.5e6 N/m, prior N(3e6, 0.5e6²), true 3.25e6.
    """
    rng = np.random.default_rng(42)
    n = 300
    x = 1e-6 * np.sin(2 * np.pi * np.outer([3, 7], np.arange(n)) / n)
    sigma = np.array([0.5, 1.0])
    data = 3.25e6 * x + sigma[:, None] * rng.standard_normal(x.shape)
    prior_mean, prior_sd = 3.0e6, 0.5e6

    grid = np.linspace(2.0e6, 4.5e6, 2001)
    posterior = grid_posterior(
        grid,
        log_likelihood(data, grid[:, None, None] * x, sigma),
        gaussian_log_prior(grid, prior_mean, prior_sd),
    )
    # Conjugate update: precisions add, the mean is the precision-weighted combination.
    w = x / sigma[:, None] ** 2
    precision = np.sum(w * x) + prior_sd**-2
    mean = (np.sum(w * data) + prior_mean / prior_sd**2) / precision
    return posterior, mean, precision**-0.5


def test_grid_posterior_matches_the_conjugate_posterior(linear_gaussian):
    posterior, mean, sd = linear_gaussian
    spacing = posterior.grid[1] - posterior.grid[0]
    assert sd > 20 * spacing and abs(mean - 3.25e6) < 4 * sd  # the grid resolves a well-posed problem

    np.testing.assert_allclose(posterior.mean, mean, rtol=1e-6)
    np.testing.assert_allclose(posterior.sd, sd, rtol=1e-6)
    assert abs(posterior.map - mean) <= spacing / 2
    low, high = posterior.hdi(0.94)
    assert abs(low - (mean - Z_94 * sd)) <= spacing
    assert abs(high - (mean + Z_94 * sd)) <= spacing
    np.testing.assert_allclose(posterior.cdf[-1], 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.interp(mean, posterior.grid, posterior.cdf), 0.5, atol=1e-3)


def test_grid_posterior_keeps_the_inputs_and_scales_the_likelihood(linear_gaussian):
    posterior, _, _ = linear_gaussian
    assert posterior.scaled_likelihood.max() == 1.0
    assert posterior.grid[np.argmax(posterior.scaled_likelihood)] == posterior.grid[np.argmax(posterior.log_likelihood)]
    np.testing.assert_allclose(posterior.prior_density, stats.norm.pdf(posterior.grid, 3.0e6, 0.5e6), rtol=1e-12)
    with pytest.raises(dataclasses.FrozenInstanceError):
        posterior.density = posterior.density * 2
    with pytest.raises(ValueError):
        posterior.density[0] = 1.0  # arrays are read-only too


def test_reduced_chi2_is_one_when_the_model_explains_the_data():
    rng = np.random.default_rng(7)
    sigma = np.array([0.1, 3.0, 20.0])
    model = rng.normal(size=(3, 4000))
    data = model + sigma[:, None] * rng.standard_normal(model.shape)
    n_obs = data.size

    # χ²/N has standard deviation √(2/N).
    assert abs(reduced_chi2(data, model, sigma) - 1) < 3 * np.sqrt(2 / n_obs)
    np.testing.assert_allclose(
        reduced_chi2(data, model, sigma, n_fitted=2), reduced_chi2(data, model, sigma) * n_obs / (n_obs - 2)
    )
    # A wrong model is far off, and grid axes broadcast.
    assert reduced_chi2(data, np.stack([model, model + sigma[:, None]]), sigma)[1] > 1.9
    with pytest.raises(ValueError, match="degrees of freedom"):
        reduced_chi2(data, model, sigma, n_fitted=n_obs)


GRID = np.linspace(0.0, 10.0, 1001)


def _gaussian_bump(center, width, height=1.0):
    return height * np.exp(-0.5 * ((GRID - center) / width) ** 2)


@pytest.mark.parametrize(
    "likelihood, min_prominence, expected",
    [
        (_gaussian_bump(5, 0.5), 0.05, 1),
        (_gaussian_bump(3, 0.4) + _gaussian_bump(7, 0.4), 0.05, 2),
        (_gaussian_bump(4, 0.5) + _gaussian_bump(8, 0.3, 0.02), 0.05, 1),  # bump below the threshold
        (_gaussian_bump(4, 0.5) + _gaussian_bump(8, 0.3, 0.02), 0.01, 2),
        (np.exp(2 * GRID), 0.05, 1),  # rising to the upper bound: the mode lies beyond the grid
        (np.exp(-2 * GRID), 0.05, 1),  # the same at the lower bound
        (_gaussian_bump(3, 0.5) + 0.5 * np.exp(3 * (GRID - 10)), 0.05, 2),  # a second mode cut by the bound
    ],
    ids=["gaussian", "two-modes", "small-bump-ignored", "small-bump-counted", "rising", "falling", "cut-mode"],
)
def test_n_peaks_counts_prominent_likelihood_peaks(likelihood, min_prominence, expected):
    posterior = grid_posterior(GRID, np.log(likelihood), 0.0)
    assert posterior.n_peaks(min_prominence) == expected


@pytest.mark.parametrize(
    "likelihood, consistent",
    [
        (_gaussian_bump(5, 0.5), True),
        (_gaussian_bump(3, 0.4) + _gaussian_bump(7, 0.4), False),
        (np.exp(2 * GRID), False),  # the best fit lies beyond the upper bound
        (np.exp(-2 * GRID), False),
        (_gaussian_bump(9.9, 0.5), True),  # close to the bound, but the peak is inside
    ],
    ids=["gaussian", "two-modes", "rising", "falling", "near-bound"],
)
def test_consistent_means_one_likelihood_peak_inside_the_grid(likelihood, consistent):
    assert grid_posterior(GRID, np.log(likelihood), 0.0).consistent() == consistent


def test_hdi_of_a_bimodal_posterior_spans_both_modes():
    posterior = grid_posterior(GRID, np.log(_gaussian_bump(3, 0.4) + _gaussian_bump(7, 0.4)), 0.0)
    low, high = posterior.hdi(0.94)
    assert low < 3 and 7 < high and posterior.n_peaks() == 2
    assert posterior.hdi(1.0) == (GRID[0], GRID[-1])


def test_huge_log_likelihoods_give_a_finite_normalized_density():
    grid = np.linspace(2.0e6, 4.5e6, 200)
    rng = np.random.default_rng(3)
    log_like = -1e6 - rng.uniform(0, 5000, grid.size)  # exp() underflows at every point
    posterior = grid_posterior(grid, log_like, gaussian_log_prior(grid, 3e6, 0.5e6))
    assert np.all(np.isfinite(posterior.density))
    np.testing.assert_allclose(np.trapezoid(posterior.density, grid), 1.0, rtol=1e-12)

    # So sharp that only one grid point keeps any probability: the posterior is that point.
    peak = 57
    spiky = -1e6 - 5e3 * (np.arange(grid.size) - peak) ** 2
    spiky[:10] = -np.inf
    posterior = grid_posterior(grid, spiky, gaussian_log_prior(grid, 3e6, 0.5e6))
    np.testing.assert_allclose(np.trapezoid(posterior.density, grid), 1.0, rtol=1e-12)
    assert posterior.map == posterior.mean == grid[peak] and posterior.sd == 0.0
    assert posterior.hdi() == (grid[peak], grid[peak]) and posterior.n_peaks() == 1


def test_minus_infinity_is_zero_probability_but_nan_and_all_minus_infinity_are_refused():
    log_like = np.where(GRID < 2, -np.inf, -0.5 * (GRID - 5) ** 2)
    posterior = grid_posterior(GRID, log_like, 0.0)
    assert np.all(posterior.density[GRID < 2] == 0) and np.all(posterior.scaled_likelihood[GRID < 2] == 0)

    with pytest.raises(ValueError, match="NaN"):
        grid_posterior(GRID, np.where(GRID < 2, np.nan, 0.0), 0.0)
    with pytest.raises(ValueError, match="zero at every grid point"):
        grid_posterior(GRID, np.full(GRID.size, -np.inf), 0.0)
    with pytest.raises(ValueError, match="increasing"):
        grid_posterior(GRID[::-1], log_like, 0.0)


def test_chi2_recovered_from_log_likelihood():
    rng = np.random.default_rng(5)
    sigma = np.array([0.5, 2.0])
    model = rng.normal(size=(2, 300))
    data = model + sigma[:, None] * rng.standard_normal((2, 300))
    chi2 = np.sum(((data - model) / sigma[:, None]) ** 2)
    assert likelihood.chi2_from_log_likelihood(likelihood.log_likelihood(data, model, sigma), sigma, 300) == pytest.approx(chi2, rel=1e-10)
