"""Instrument offsets and gains integrated out: against the multivariate Normal they define."""

import numpy as np
import pytest
from scipy import stats

from newdyn import likelihood, sensors

RNG = np.random.default_rng(11)
N = 60
MODEL = np.stack([np.sin(np.linspace(0, 7, N)) * 3e-6 + 1e-6, 50.0 + np.cos(np.linspace(0, 5, N))])  # a probe [m], a speed [rad/s]
SIGMA = np.array([2e-8, 0.05])
SCALE = np.array([[5e-8, 0.01], [0.0, 0.002]])  # the speed sensor: a gain error only


def readings(offset, gain):
    return offset[:, None] + gain[:, None] * MODEL + SIGMA[:, None] * RNG.standard_normal(MODEL.shape)


def test_the_marginal_likelihood_is_the_normal_density_with_the_instruments_covariance():
    data = readings(np.array([4e-8, 0.0]), np.array([1.01, 0.999]))
    expected, quadratic = [], []
    for c in range(2):
        design = np.column_stack([np.full(N, SCALE[c, 0]), SCALE[c, 1] * MODEL[c]])
        covariance = SIGMA[c] ** 2 * np.eye(N) + design @ design.T
        expected.append(stats.multivariate_normal(MODEL[c], covariance).logpdf(data[c]))
        residual = data[c] - MODEL[c]
        quadratic.append(residual @ np.linalg.solve(covariance, residual))
    assert sensors.log_likelihood(data, MODEL, SIGMA, SCALE, per_channel=True) == pytest.approx(expected, rel=1e-10)
    # What least squares minimizes: n + 2 numbers per channel whose squares sum to rᵀC⁻¹r.
    z = sensors.standardized_residuals(data, MODEL, SIGMA, SCALE)
    assert z.shape == (2, N + 2) and np.sum(z**2, axis=-1) == pytest.approx(quadratic, rel=1e-9)


def test_without_instrument_errors_it_is_the_plain_gaussian_likelihood():
    data = readings(np.zeros(2), np.ones(2))
    plain = likelihood.log_likelihood(data, MODEL, SIGMA, per_channel=True)
    assert sensors.log_likelihood(data, MODEL, SIGMA, np.zeros((2, 2)), per_channel=True) == pytest.approx(plain, rel=1e-13)


def test_the_estimates_are_the_gaussian_posterior_of_offset_and_gain():
    data = readings(np.array([4e-8, 0.0]), np.array([1.01, 0.999]))
    found = sensors.estimate(data, MODEL, SIGMA, SCALE)
    for c in range(2):
        # Conditioning the joint Normal of (o, g, y) on y: the textbook linear-Gaussian posterior, over the
        # quantities with a prior spread (the others stay at 0 and 1 with no spread).
        fitted = SCALE[c] > 0
        design = np.column_stack([np.ones(N), MODEL[c]])[:, fitted]
        prior_precision = np.diag(SCALE[c][fitted] ** -2.0)
        covariance = np.linalg.inv(prior_precision + design.T @ design / SIGMA[c] ** 2)
        mean = covariance @ (prior_precision @ np.array([0.0, 1.0])[fitted] + design.T @ data[c] / SIGMA[c] ** 2)
        expected_mean, expected_sd = np.array([0.0, 1.0]), np.zeros(2)
        expected_mean[fitted], expected_sd[fitted] = mean, np.sqrt(np.diag(covariance))
        assert [found["offset"][c], found["gain"][c]] == pytest.approx(expected_mean, rel=1e-8, abs=1e-20)
        assert [found["offset_sd"][c], found["gain_sd"][c]] == pytest.approx(expected_sd, rel=1e-6, abs=1e-20)


def test_leading_axes_broadcast_like_the_plain_likelihood():
    data = readings(np.zeros(2), np.ones(2))
    models = np.stack([MODEL, 1.001 * MODEL, MODEL + 1e-8])
    together = sensors.log_likelihood(data, models, SIGMA, SCALE)
    assert together == pytest.approx([sensors.log_likelihood(data, m, SIGMA, SCALE) for m in models], rel=1e-13)


def test_a_sensor_prior_must_be_a_finite_spread():
    with pytest.raises(ValueError, match="gain_sd must be a finite number >= 0"):
        sensors.Sensor(offset_sd=1e-8, gain_sd=-0.01)


def test_a_probe_offset_within_its_datasheet_is_not_a_misfit_but_a_stiffer_shaft_still_is():
    from newdyn import hypotheses, model, noise, simulation

    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=500)
    channels = ("b1_x", "w1")
    healthy = hypotheses.Hypothesis("healthy", "healthy")
    scale = sensors.scales({"b1_x": sensors.Sensor(offset_sd=5e-8, gain_sd=0.01), "w1": sensors.Sensor(gain_sd=0.002)}, channels)

    def chi2(truth, offset):
        clean = simulation.simulate(model.complete(truth), sampling, channels)
        data, sigma = noise.add_noise(clean, channels, 40.0, 2)
        data[0] += offset * np.std(clean[0])
        return [hypotheses.fit(healthy, data, sigma, model.complete({}), sampling, channels, sensor_scale=s).chi2_red
                for s in (None, scale)]

    exact, with_instruments = chi2({}, 0.2)
    assert exact > 10 and with_instruments < 1.1
    exact, with_instruments = chi2({"kT3": 2.2e6}, 0.0)  # an offset and a gain cannot take a resonance's shift
    assert exact > 4 and with_instruments == pytest.approx(exact, rel=0.01)
