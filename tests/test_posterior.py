"""Posteriors around a Laplace approximation against closed forms: quadrature must be exact to its resolution whatever
the shape, importance sampling must recover a posterior the approximation is off from, and refuse to vouch for one it
misses."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from newdyn import posterior

SETTINGS = posterior.PosteriorSettings(seed=3, batch=2000, max_draws=8000)


def gaussian(mean, cov):
    """Log-likelihood of a correlated Gaussian posterior (flat prior on a wide box), batched."""
    precision = np.linalg.inv(cov)

    def log_likelihood(theta):
        d = theta - mean
        return -0.5 * np.einsum("ni,ij,nj->n", d, precision, d)

    return log_likelihood


def counted(log_likelihood):
    """``log_likelihood`` and the list of the batch sizes it is called with, as simulations are counted."""
    calls = []

    def wrapped(theta):
        calls.append(len(theta))
        return log_likelihood(theta)

    return wrapped, calls


def box(low, high):
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    return lambda theta: np.where(np.all((theta >= low) & (theta <= high), axis=1), 0.0, -np.inf)


def moments(idata, names):
    draws = np.column_stack([idata.posterior[n].values.ravel() for n in names])
    return draws.mean(axis=0), draws.std(axis=0)


STIFFNESS_AND_DEPTH = (np.array([3.0e6, 0.35]), np.array([8.0e3, 1.0e-3]))  # scales as far apart as kT1 and a crack's α


def test_quadrature_recovers_a_correlated_gaussian_from_an_approximation_off_centre_and_too_narrow():
    mean, sd = STIFFNESS_AND_DEPTH
    cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * np.outer(sd, sd)
    idata = posterior.sample(gaussian(mean, cov), box([0, 0], [1e7, 1]), ["k", "a"], mean + np.array([1.0, -1.0]) * sd,
                             0.5**2 * cov, SETTINGS)
    assert idata.attrs["method"] == "quadrature" and idata.attrs["converged"] == 1
    got_mean, got_sd = moments(idata, ["k", "a"])
    # the lattice's moments are exact to its resolution; the resampled draws add their Monte Carlo error
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(SETTINGS.batch))
    np.testing.assert_allclose(got_sd, sd, rtol=0.06)


@pytest.mark.parametrize("too_wide, split", [(1.0, False), (2.0, False), (4.0, True)])
def test_quadrature_splits_its_cells_only_where_its_lattice_disagrees_with_the_lattice_of_its_even_points(too_wide, split):
    """The first lattice, ±5 of the approximation's sds at half of one, checked against its own points of even index
    (the lattice at one sd, no simulation more): a Gaussian the approximation fits, or is twice too wide for, is
    resolved without a split (and without growing: its lattice's edge is light); one four times narrower than the
    approximation, its sd half a step, is split, and resolved as well."""
    mean, sd = STIFFNESS_AND_DEPTH
    cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * np.outer(sd, sd)
    evaluated = []

    def log_posterior(theta):
        evaluated.append(len(theta))
        log_likelihood = gaussian(mean, cov)(theta)
        return log_likelihood, log_likelihood, np.empty((len(theta), 0))

    theta, log_weight, *_, found = posterior._quadrature(log_posterior, posterior._Whitened.of(mean, too_wide**2 * cov), np.zeros(0))
    first_lattice = (2 * round(posterior.HALF_WIDTH / posterior.STEP) + 1) ** 2
    assert found["converged"] and (found["step"] < posterior.STEP) == split
    assert (sum(evaluated) > first_lattice) == split and found["n_points"] == sum(evaluated)
    weight = np.exp(log_weight)
    got_mean = weight @ theta
    got_sd = np.sqrt(weight @ (theta - got_mean) ** 2)
    np.testing.assert_array_less(np.abs(got_mean - mean), 0.01 * sd)  # the midpoint rule on a Gaussian: far below its bound
    np.testing.assert_allclose(got_sd, sd, rtol=0.01)


def test_quadrature_lays_its_lattice_again_where_the_approximation_is_far_too_narrow():
    """An approximation forty times too narrow: the widest lattice about it, ±30 of its sds, spans under one sd of the
    posterior; laid again about that lattice's own moments, the quadrature is verified and exact to its resolution."""
    mean, sd = STIFFNESS_AND_DEPTH
    cov = np.array([[1.0, 0.6], [0.6, 1.0]]) * np.outer(sd, sd)
    idata = posterior.sample(gaussian(mean, cov), box([0, 0], [1e7, 1]), ["k", "a"], mean + np.array([0.3, 0.2]) * sd,
                             cov / 40**2, SETTINGS)
    assert idata.attrs["method"] == "quadrature" and idata.attrs["converged"] == 1, idata.attrs["reason"]
    assert "quadrature about the Laplace approximation" in idata.attrs["tried"]
    got_mean, got_sd = moments(idata, ["k", "a"])
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(SETTINGS.batch))
    np.testing.assert_allclose(got_sd, sd, rtol=0.06)


def test_quadrature_grows_its_lattice_along_a_ridge_past_its_first_extent_and_nowhere_else():
    """A Gaussian ten times wider than the approximation along one diagonal and as narrow across: the lattice grows
    from ±5 sds along the ridge only, to the cells about it (far fewer than the box around them), and is exact."""
    rotation = np.array([[1.0, -1.0], [1.0, 1.0]]) / np.sqrt(2)
    cov = rotation @ np.diag([10.0**2, 1.0]) @ rotation.T
    evaluated = []

    def log_posterior(theta):
        evaluated.append(len(theta))
        log_likelihood = gaussian(np.zeros(2), cov)(theta)
        return log_likelihood, log_likelihood, np.empty((len(theta), 0))

    theta, log_weight, *_, found = posterior._quadrature(log_posterior, posterior._Whitened.of(np.zeros(2), np.eye(2)), np.zeros(0))
    reach = 10 * 5.3 / np.sqrt(2) / posterior.STEP  # the ridge's ±5.3 sds (the first lattice's extent) along each axis, in cells
    assert found["converged"] and found["edge_mass"] < posterior.EDGE_MASS
    assert sum(evaluated) < 0.2 * (2 * reach + 1) ** 2 and len(evaluated) > 2
    weight = np.exp(log_weight)
    got_mean = weight @ theta
    np.testing.assert_array_less(np.abs(got_mean), 0.01 * 10)
    np.testing.assert_allclose(np.cov(theta, rowvar=False, aweights=weight, ddof=0), cov, rtol=0.01, atol=0.01)


def test_quadrature_after_an_importance_batch_that_missed_is_laid_about_its_draws_at_fewer_points(monkeypatch):
    """An approximation four times too narrow: its importance batch misses (k̂ > 0.5) but its weighted draws place the
    posterior; the lattice laid about them needs fewer simulations than one grown from the approximation, and both
    are exact."""
    mean, sd = STIFFNESS_AND_DEPTH
    cov = np.array([[1.0, 0.95], [0.95, 1.0]]) * np.outer(sd, sd)
    found = {}
    for laid_on_draws in (True, False):
        if not laid_on_draws:
            monkeypatch.setattr(posterior, "LAID_ON_DRAWS_ESS", np.inf)
        log_likelihood, calls = counted(gaussian(mean, cov))
        idata = posterior.sample(log_likelihood, box([0, 0], [1e7, 1]), ["k", "a"], mean, cov / 4**2, SETTINGS)
        assert idata.attrs["method"] == "quadrature" and idata.attrs["converged"] == 1, idata.attrs["reason"]
        got_mean, got_sd = moments(idata, ["k", "a"])
        np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(SETTINGS.batch))
        np.testing.assert_allclose(got_sd, sd, rtol=0.06)
        found[laid_on_draws] = sum(calls)
    assert found[True] < 0.7 * found[False]


def test_a_lattice_is_laid_again_only_about_weights_that_span_every_parameter():
    equal = np.log(np.full(3, 1 / 3))
    for degenerate in ([[0, 0], [1, 1], [2, 2]], [[1, 2], [1, 2], [1, 2]]):  # on a line, at one point
        assert posterior._recentred(np.array(degenerate, dtype=float), equal) is None
    spread = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])
    recentred = posterior._recentred(spread, equal)
    np.testing.assert_allclose(recentred.theta(np.zeros((1, 2)))[0], [1.0, 1.0])
    np.testing.assert_allclose(recentred.scale, np.sqrt(2.0))  # each coordinate's variance: (1 + 4 + 1) / 3


@pytest.mark.parametrize("ess_min, verified", [(400.0, False), (200.0, True)])
def test_a_posterior_nothing_rests_on_costs_one_small_batch_of_importance_sampling_and_never_quadrature(ess_min, verified):
    """Unverified (``verify=False``): from an approximation off centre and too narrow, one batch of
    :data:`~newdyn.posterior.UNVERIFIED_BATCH` draws and no lattice; from the exact one, that batch's draws have the
    posterior's moments, and verify it where they reach the effective draws asked for."""
    mean, sd = STIFFNESS_AND_DEPTH
    cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * np.outer(sd, sd)
    settings = replace(SETTINGS, ess_min=ess_min)
    likelihood, calls = counted(gaussian(mean, cov))
    off = posterior.sample(likelihood, box([0, 0], [1e7, 1]), ["k", "a"], mean + np.array([1.0, -1.0]) * sd, 0.5**2 * cov, settings,
                           verify=False)
    assert off.attrs["method"] == "importance sampling" and off.attrs["n_proposals"] == posterior.UNVERIFIED_BATCH == sum(calls)
    assert off.attrs["converged"] == 0
    exact = posterior.sample(gaussian(mean, cov), box([0, 0], [1e7, 1]), ["k", "a"], mean, cov, settings, verify=False)
    assert exact.attrs["method"] == "importance sampling" and exact.attrs["converged"] == int(verified)
    assert exact.posterior.sizes["draw"] == SETTINGS.batch  # the draws kept, equally weighted, as many as a verified batch's
    got_mean, got_sd = moments(exact, ["k", "a"])
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(posterior.UNVERIFIED_BATCH))
    np.testing.assert_allclose(got_sd, sd, rtol=0.15)


def test_quadrature_follows_a_thin_curved_ridge_a_gaussian_proposal_misses():
    """x ~ N(0, 1), y | x ~ N(b (x² − 1), w²): a banana whose ridge bends 8 of its widths away from its tangent at
    two sds.  E[y] = 0 and sd(y) = √(2 b² + w²), against −b and w at the mode, where the approximation sits."""
    b, w = 0.2, 0.1

    def banana(theta):
        x, y = theta[:, 0], theta[:, 1]
        return -0.5 * x**2 - 0.5 * ((y - b * (x**2 - 1)) / w) ** 2

    idata = posterior.sample(banana, box([-50, -50], [50, 50]), ["x", "y"], np.array([0.0, -b]), np.diag([1.0, w**2]), SETTINGS)
    assert idata.attrs["converged"] == 1, idata.attrs["reason"]
    got_mean, got_sd = moments(idata, ["x", "y"])
    exact_sd = np.sqrt(2 * b**2 + w**2)
    assert got_mean[1] == pytest.approx(0.0, abs=4 * exact_sd / np.sqrt(SETTINGS.batch))
    assert got_sd[1] == pytest.approx(exact_sd, rel=0.06) and got_sd[0] == pytest.approx(1.0, rel=0.06)


def test_quadrature_of_a_posterior_cut_by_its_prior_bound_has_the_truncated_normals_mean():
    """A fault's severity piled against zero: N(0.001, 0.002²) truncated to [0, 1], the approximation at the bound."""
    mu, sigma = 0.001, 0.002
    idata = posterior.sample(lambda t: -0.5 * ((t[:, 0] - mu) / sigma) ** 2, box([0], [1]), ["alpha"], np.array([0.0]),
                             np.array([[sigma**2]]), SETTINGS)
    exact = stats.truncnorm((0 - mu) / sigma, (1 - mu) / sigma, loc=mu, scale=sigma)
    got = idata.posterior["alpha"].values.ravel()
    assert idata.attrs["converged"] == 1
    assert got.min() >= 0.0  # draws spread over their cells stay inside the support
    assert got.mean() == pytest.approx(exact.mean(), abs=4 * exact.std() / np.sqrt(SETTINGS.batch))


def test_importance_sampling_recovers_a_correlated_gaussian_in_three_parameters():
    mean, sd = np.array([3.0e6, 0.35, 2000.0]), np.array([8.0e3, 1.0e-3, 0.5])
    corr = np.array([[1.0, -0.9, 0.3], [-0.9, 1.0, -0.2], [0.3, -0.2, 1.0]])
    cov = corr * np.outer(sd, sd)
    idata = posterior.sample(gaussian(mean, cov), box([0, 0, 0], [1e7, 1, 1e4]), ["k", "a", "t"],
                             mean + np.array([0.3, -0.3, 0.2]) * sd, 0.8**2 * cov, SETTINGS)
    assert idata.attrs["method"] == "importance sampling"
    assert idata.attrs["converged"] == 1 and idata.attrs["pareto_k"] <= 0.7
    ess = idata.attrs["ess_bulk"]
    got_mean, got_sd = moments(idata, ["k", "a", "t"])
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(ess))
    np.testing.assert_allclose(got_sd, sd, rtol=4 / np.sqrt(2 * ess))


@pytest.mark.parametrize(("narrower", "missed"), [(4, "pareto_k"), (3, "ess")])
def test_importance_sampling_fits_its_proposal_again_where_the_approximation_is_too_narrow(narrower, missed):
    """An approximation a quarter as wide as the posterior: k̂ says the first batch misses it; a third as wide: k̂
    passes but the batch leaves too few effective draws.  Fitted again to that batch's weighted draws, the proposal
    verifies the posterior's closed-form moments with one batch of its own: two batches in all, where more draws of
    the approximation would have needed the most."""
    mean, sd = np.array([3.0e6, 0.35, 2000.0]), np.array([8.0e3, 1.0e-3, 0.5])
    cov = np.array([[1.0, -0.9, 0.3], [-0.9, 1.0, -0.2], [0.3, -0.2, 1.0]]) * np.outer(sd, sd)
    likelihood, calls = counted(gaussian(mean, cov))
    idata = posterior.sample(likelihood, box([0, 0, 0], [1e7, 1, 1e4]), ["k", "a", "t"],
                             mean + np.array([0.5, -0.5, 0.3]) * sd, cov / narrower**2, SETTINGS)
    assert idata.attrs["converged"] == 1 and idata.attrs["refits"] == 1, idata.attrs["reason"]
    assert idata.attrs["tried"].startswith(f"proposal fitted again to its weighted draws after: {missed}")
    assert idata.attrs["tried"].endswith(f"({SETTINGS.batch} draws)")
    assert sum(calls) == 2 * SETTINGS.batch and idata.attrs["n_proposals"] == SETTINGS.batch
    ess = idata.attrs["ess_bulk"]
    got_mean, got_sd = moments(idata, ["k", "a", "t"])
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * sd / np.sqrt(ess))
    np.testing.assert_allclose(got_sd, sd, rtol=4 / np.sqrt(2 * ess))


@pytest.mark.parametrize("short_of_optimum", [True, False])
def test_importance_sampling_stops_before_fitting_its_proposal_again_where_a_draw_beats_the_fit(short_of_optimum):
    """An approximation a quarter as wide as the posterior, about a point 10 nats short of its optimum, as a fit that
    stopped short leaves it.  Told to stop where a draw's log-likelihood beats the fit's by 1, the sampler returns its
    first batch, unverified and saying why, for the caller to fit again from its best draw: no proposal is fitted
    again.  Where no draw can beat it by that much (the bar above the optimum's log-likelihood, 0), it samples as it
    would untold, to the same draws."""
    mean, sd = np.array([3.0e6, 0.35, 2000.0]), np.array([8.0e3, 1.0e-3, 0.5])
    cov = np.array([[1.0, -0.9, 0.3], [-0.9, 1.0, -0.2], [0.3, -0.2, 1.0]]) * np.outer(sd, sd)
    fitted = mean + np.array([1.0, 1.0, 0.0]) * sd
    fit_log_likelihood = float(gaussian(mean, cov)(fitted[None])[0])
    assert fit_log_likelihood < -10.0
    bar = fit_log_likelihood + 1.0 if short_of_optimum else 0.5

    def run(refit_below):
        likelihood, calls = counted(gaussian(mean, cov))
        idata = posterior.sample(likelihood, box([0, 0, 0], [1e7, 1, 1e4]), ["k", "a", "t"], fitted, cov / 16, SETTINGS,
                                 refit_below=refit_below)
        return idata, sum(calls)

    idata, simulated = run(bar)
    best = float(idata.weighted["log_likelihood"].max())
    if short_of_optimum:
        assert idata.attrs["converged"] == 0 and idata.attrs["refits"] == 0 and simulated == SETTINGS.batch
        assert idata.attrs["reason"].endswith("; a draw fits better than the approximation's optimum")
        assert best > bar
    else:
        untold, untold_simulated = run(None)
        assert idata.attrs["refits"] >= 1 and simulated == untold_simulated
        np.testing.assert_array_equal(idata.posterior["k"].values, untold.posterior["k"].values)


def test_importance_sampling_refuses_a_posterior_with_a_second_mode_in_the_approximations_tail():
    """As much mass again 5 sds from where the approximation sits, within the proposal's reach but far in its
    tail: the few draws there carry huge weights, and k̂ says the estimate cannot be trusted."""

    def two_modes(theta):
        x = theta[:, 0]
        return np.logaddexp(-0.5 * x**2, -0.5 * ((x - 5.0) / 0.5) ** 2 - np.log(0.5)) - 0.5 * np.sum(theta[:, 1:] ** 2, axis=1)

    idata = posterior.sample(two_modes, box([-100] * 3, [100] * 3), ["x", "u", "v"], np.zeros(3), np.eye(3),
                             posterior.PosteriorSettings(seed=1, batch=1000, max_draws=4000))
    assert idata.attrs["converged"] == 0 and idata.attrs["pareto_k"] > 0.7
    assert "the proposal fitted again misses the posterior" in idata.attrs["reason"]  # whose proposal, in words
    assert "the Laplace approximation misses the posterior" in idata.attrs["tried"]
    assert idata.attrs["refits"] == posterior.REFITS  # a proposal fitted to draws that outweigh each other misses too


@pytest.mark.parametrize("k", [2, 3])
def test_the_same_seed_gives_the_same_draws(k):
    run = [posterior.sample(gaussian(np.zeros(k), np.eye(k)), box([-9] * k, [9] * k), list("abc"[:k]), np.zeros(k), np.eye(k), SETTINGS)
           for _ in range(2)]
    np.testing.assert_array_equal(run[0].posterior["a"].values, run[1].posterior["a"].values)


@pytest.mark.parametrize(("narrower", "method"), [(1.0, "importance sampling"), (4.0, "quadrature")])
def test_a_nuisance_integrated_out_by_the_likelihood_moves_the_others_by_its_curvature_and_is_drawn_from_its_conditional(
        narrower, method):
    # log p(θ, φ) = −½ θ'Σ⁻¹θ − ½ S(θ) (φ − a θ₀)², S(θ) = s₀ exp(c θ₁): integrating φ out adds ½ log 2π/S(θ) = −½ c θ₁ +
    # const, which moves θ's mean to −½ c Σ e₁; given θ, φ is normal about a θ₀ with variance 1/S(θ).
    cov, a, s0, c = np.array([[1.0, 0.5], [0.5, 2.0]]), 3.0, 400.0, 0.8

    def profiled(theta):
        curvature = s0 * np.exp(c * theta[:, 1])
        return posterior.Profiled(gaussian(np.zeros(2), cov)(theta), 0.5 * np.log(2 * np.pi / curvature),
                                  (a * theta[:, 0])[:, None], (1 / np.sqrt(curvature))[:, None])

    idata = posterior.sample(profiled, box([-20, -20], [20, 20]), ["t0", "t1"], np.zeros(2), cov / narrower**2, SETTINGS,
                             nuisance=["phi"])
    assert idata.attrs["method"] == method and idata.attrs["converged"] == 1
    mean = cov @ np.array([0.0, -0.5 * c])
    got_mean, got_sd = moments(idata, ["t0", "t1"])
    np.testing.assert_array_less(np.abs(got_mean - mean), 4 * np.sqrt(np.diag(cov) / SETTINGS.batch))
    np.testing.assert_allclose(got_sd, np.sqrt(np.diag(cov)), rtol=0.06)  # a linear term moves a Gaussian, not its spread
    phi_mean = a * mean[0]
    phi_variance = a**2 * cov[0, 0] + np.exp(-c * mean[1] + c**2 * cov[1, 1] / 2) / s0  # E[1/S(θ)] of a lognormal
    phi = idata.posterior["phi"].values.ravel()
    assert abs(phi.mean() - phi_mean) < 4 * np.sqrt(phi_variance / SETTINGS.batch)
    np.testing.assert_allclose(phi.std(), np.sqrt(phi_variance), rtol=0.06)
    # every lattice point carries the nuisance's conditional mean
    np.testing.assert_allclose(idata.weighted["phi"].values, a * idata.weighted["t0"].values)
