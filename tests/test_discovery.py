"""Estimating a missing force: the closed forms of Bayesian linear regression, and what they decide."""

import math

import numpy as np
import pytest
from scipy import integrate, stats

from newdyn.discovery import force

SIGMA = np.array([0.5, 2.0])


def smooth_sensitivity(rng, n_samples=120, n_basis=30, decay=8.0):
    """(2, n_samples, n_basis): each channel's decaying, oscillating response to pulses at the basis times."""
    t = np.arange(n_samples)[:, None] - np.linspace(0, n_samples - 10, n_basis)[None, :]
    channels = []
    for _ in SIGMA:
        frequency, gain = rng.uniform(0.1, 0.4), rng.uniform(0.5, 2.0)
        channels.append(np.where(t >= 0, gain * np.exp(-t / decay) * np.sin(frequency * t + 0.3), 0.0))
    return np.stack(channels)


def noise(rng, n_samples=120):
    return rng.normal(size=(len(SIGMA), n_samples)) * SIGMA[:, None]


@pytest.mark.parametrize("n_basis", [30, 300])  # fewer pulses than data, and more
def test_evidence_and_posterior_at_one_scale_are_the_gaussian_closed_forms(n_basis):
    rng = np.random.default_rng(1)
    g = smooth_sensitivity(rng, n_basis=n_basis)
    residual = np.einsum("ctj,j->ct", g, rng.normal(0, 3.0, n_basis)) + noise(rng)
    s = 2.5
    result = force.estimate("here", residual, SIGMA, g, np.arange(n_basis), (s, s * (1 + 1e-10)))
    flat = g.reshape(residual.size, -1)
    noise_cov = np.diag(np.repeat(SIGMA**2, residual.shape[1]))
    expected = stats.multivariate_normal(np.zeros(residual.size), noise_cov + s**2 * flat @ flat.T).logpdf(residual.ravel())
    assert result.log_evidence == pytest.approx(expected, abs=1e-6)
    precision = flat.T @ np.linalg.solve(noise_cov, flat) + np.eye(n_basis) / s**2
    covariance = np.linalg.inv(precision)
    assert result.mean == pytest.approx(covariance @ flat.T @ np.linalg.solve(noise_cov, residual.ravel()), abs=1e-8)
    assert result.sd == pytest.approx(np.sqrt(np.diag(covariance)), rel=1e-7)
    without = stats.multivariate_normal(np.zeros(residual.size), noise_cov).logpdf(residual.ravel())
    assert result.log_bayes_factor == pytest.approx(expected - without, abs=1e-6)


def test_the_prior_scale_is_marginalized_over_its_log_uniform_prior():
    rng = np.random.default_rng(2)
    g = smooth_sensitivity(rng)
    residual = np.einsum("ctj,j->ct", g, rng.normal(0, 1.0, g.shape[2])) + noise(rng)
    low, high = 0.01, 100.0
    result = force.estimate("here", residual, SIGMA, g, np.arange(g.shape[2]), (low, high))

    def log_evidence_at(log_s):
        return force.estimate("here", residual, SIGMA, g, np.arange(g.shape[2]), (math.exp(log_s), math.exp(log_s) * (1 + 1e-10))).log_evidence

    peak = max(log_evidence_at(x) for x in np.linspace(math.log(low), math.log(high), 41))
    integral, _ = integrate.quad(lambda x: math.exp(log_evidence_at(x) - peak), math.log(low), math.log(high), limit=200)
    assert result.log_evidence == pytest.approx(peak + math.log(integral / (math.log(high) - math.log(low))), abs=1e-3)


def test_the_place_the_force_acts_on_wins_and_the_force_is_recovered_within_its_uncertainty():
    rng = np.random.default_rng(3)
    at = smooth_sensitivity(rng)
    elsewhere = at * np.array([1.0, 3.0])[:, None, None]  # seen through the same channels, in another proportion
    times = np.arange(at.shape[2])
    truth = 4.0 * np.sin(times / 3.0)
    residual = np.einsum("ctj,j->ct", at, truth) + noise(rng)
    right = force.estimate("right", residual, SIGMA, at, times, (0.01, 100.0))
    wrong = force.estimate("wrong", residual, SIGMA, elsewhere, times, (0.01, 100.0))
    assert right.log_evidence - wrong.log_evidence > 50 and right.log_bayes_factor > 50
    assert right.chi2_before > 3 and right.chi2_after < 1.0  # the fitted force absorbs a little noise too
    inside = np.abs(right.mean - truth) <= 2 * right.sd
    assert inside.mean() >= 0.9


def test_noise_alone_is_not_read_as_a_force():
    """The Occam factor: with no force in the residual, adding one lowers the evidence."""
    g = smooth_sensitivity(np.random.default_rng(4))
    factors = [force.estimate("here", noise(np.random.default_rng(seed)), SIGMA, g, np.arange(g.shape[2]), (0.01, 100.0)).log_bayes_factor
               for seed in range(20)]
    assert max(factors) < 1.0 and np.median(factors) < 0


def test_bad_shapes_and_scale_ranges_are_refused():
    g = smooth_sensitivity(np.random.default_rng(5))
    residual = np.zeros(g.shape[:2])
    with pytest.raises(ValueError, match="sensitivity must be"):
        force.estimate("here", residual, SIGMA, g[:, :-1], np.arange(g.shape[2]), (0.1, 1.0))
    with pytest.raises(ValueError, match="sigma must be"):
        force.estimate("here", residual, np.array([1.0, -1.0]), g, np.arange(g.shape[2]), (0.1, 1.0))
    with pytest.raises(ValueError, match="times must"):
        force.estimate("here", residual, SIGMA, g, np.arange(g.shape[2] - 1), (0.1, 1.0))
    with pytest.raises(ValueError, match="scale_range"):
        force.estimate("here", residual, SIGMA, g, np.arange(g.shape[2]), (1.0, 0.1))
