"""Instrument offsets, gains and delays integrated out: against the multivariate Normal they define and
quadrature over the delay."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from newdyn import likelihood, noise, sensors, slots

RNG = np.random.default_rng(11)
N = 60
MODEL = np.stack([np.sin(np.linspace(0, 7, N)) * 3e-6 + 1e-6, 50.0 + np.cos(np.linspace(0, 5, N))])  # a probe [m], a speed [rad/s]
SIGMA = np.array([2e-8, 0.05])
FS = 5000.0
SCALE = np.array([[5e-8, 0.01, 0.0], [0.0, 0.002, 0.0]])  # the speed sensor: a gain error only
INSTRUMENTS = sensors.Instruments(SCALE, FS)


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
    assert sensors.log_likelihood(data, MODEL, SIGMA, INSTRUMENTS, per_channel=True) == pytest.approx(expected, rel=1e-10)
    # What least squares minimizes: n + 2 numbers per channel whose squares sum to rᵀC⁻¹r.
    z = sensors.standardized_residuals(data, MODEL, SIGMA, INSTRUMENTS)
    assert z.shape == (2, N + 3) and np.sum(z**2, axis=-1) == pytest.approx(quadratic, rel=1e-9)


def test_with_coloured_noise_it_is_the_normal_density_of_the_whitened_readings():
    """AR(1) noise of stationary variance σ² (covariance σ²φ^|i−j|) under offset and gain errors: the likelihood is
    the density of W y, W the whitening filter, whose covariance is W (σ²R + BBᵀ) Wᵀ, and least squares sees it."""
    phi = 0.7
    colour = noise.Colour(np.full((2, 1), phi), np.full(2, np.sqrt(1 - phi**2)))
    coloured = sensors.Instruments(SCALE, FS, colour)
    lags = np.abs(np.subtract.outer(np.arange(N), np.arange(N)))
    whitening = np.eye(N)[1:] - phi * np.eye(N)[:-1]
    data = readings(np.array([4e-8, 0.0]), np.array([1.01, 0.999]))
    expected, quadratic = [], []
    for c in range(2):
        design = np.column_stack([np.full(N, SCALE[c, 0]), SCALE[c, 1] * MODEL[c]])
        covariance = whitening @ (SIGMA[c] ** 2 * phi**lags + design @ design.T) @ whitening.T
        expected.append(stats.multivariate_normal(whitening @ MODEL[c], covariance).logpdf(whitening @ data[c]))
        residual = whitening @ (data[c] - MODEL[c])
        quadratic.append(residual @ np.linalg.solve(covariance, residual))
    assert sensors.log_likelihood(data, MODEL, SIGMA, coloured, per_channel=True) == pytest.approx(expected, rel=1e-10)
    z = sensors.standardized_residuals(data, MODEL, SIGMA, coloured)
    assert z.shape == (2, N - 1 + 3) and np.sum(z**2, axis=-1) == pytest.approx(quadratic, rel=1e-9)
    # the readings stay in the channel's units: what o + g·m is, whitened or not
    assert sensors.reading(data, MODEL, SIGMA, coloured) == pytest.approx(
        sensors.estimate(data, MODEL, SIGMA, coloured)["offset"][:, None]
        + sensors.estimate(data, MODEL, SIGMA, coloured)["gain"][:, None] * MODEL, rel=1e-12)


def test_without_instrument_errors_it_is_the_plain_gaussian_likelihood():
    data = readings(np.zeros(2), np.ones(2))
    plain = likelihood.log_likelihood(data, MODEL, SIGMA, per_channel=True)
    assert sensors.log_likelihood(data, MODEL, SIGMA, sensors.Instruments(np.zeros((2, 3)), FS), per_channel=True) == pytest.approx(plain, rel=1e-13)
    assert sensors.Instruments.of({}, ("b1_x", "w1"), FS) is None and sensors.reading(data, MODEL, SIGMA, None) is MODEL


def test_the_estimates_are_the_gaussian_posterior_of_offset_and_gain():
    data = readings(np.array([4e-8, 0.0]), np.array([1.01, 0.999]))
    found = sensors.estimate(data, MODEL, SIGMA, INSTRUMENTS)
    for c in range(2):
        # Conditioning the joint Normal of (o, g, y) on y: the textbook linear-Gaussian posterior, over the
        # quantities with a prior spread (the others stay at 0 and 1 with no spread).
        fitted = SCALE[c, :2] > 0
        design = np.column_stack([np.ones(N), MODEL[c]])[:, fitted]
        prior_precision = np.diag(SCALE[c, :2][fitted] ** -2.0)
        covariance = np.linalg.inv(prior_precision + design.T @ design / SIGMA[c] ** 2)
        mean = covariance @ (prior_precision @ np.array([0.0, 1.0])[fitted] + design.T @ data[c] / SIGMA[c] ** 2)
        expected_mean, expected_sd = np.array([0.0, 1.0]), np.zeros(2)
        expected_mean[fitted], expected_sd[fitted] = mean, np.sqrt(np.diag(covariance))
        assert [found["offset"][c], found["gain"][c]] == pytest.approx(expected_mean, rel=1e-8, abs=1e-20)
        assert [found["offset_sd"][c], found["gain_sd"][c]] == pytest.approx(expected_sd, rel=1e-6, abs=1e-20)


def test_leading_axes_broadcast_like_the_plain_likelihood():
    data = readings(np.zeros(2), np.ones(2))
    models = np.stack([MODEL, 1.001 * MODEL, MODEL + 1e-8])
    delayed = sensors.Instruments(SCALE + [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], FS)
    for instruments in (INSTRUMENTS, delayed):
        together = sensors.log_likelihood(data, models, SIGMA, instruments)
        assert together == pytest.approx([sensors.log_likelihood(data, m, SIGMA, instruments) for m in models], rel=1e-12)


def test_a_window_of_the_record_gives_the_bits_of_the_same_samples_copied():
    """A fit's first windows see ``data[:, :n]``, a view with the record's row stride: the likelihood, the residuals least
    squares minimizes and the instruments' reading are those of the same samples in an array of their own, to the bit
    (the compiled sums, reassociated for SIMD, would otherwise add them in another order and compile once more)."""
    record = np.concatenate([readings(np.array([4e-8, 0.0]), np.array([1.01, 0.999]))] * 3, axis=1)
    instruments = sensors.Instruments(np.array([[5e-8, 0.01, 0.4], [0.02, 0.002, 0.3]]), FS)
    models = MODEL + 1e-3 * MODEL * RNG.standard_normal((8, *MODEL.shape))
    window, copied = record[:, :N], np.array(record[:, :N])
    assert not window.flags.c_contiguous
    for function in (sensors.log_likelihood, sensors.standardized_residuals, sensors.reading):
        assert np.array_equal(function(window, models, SIGMA, instruments), function(copied, models, SIGMA, instruments))


@pytest.mark.parametrize("late", [0.0, 0.37, -1.6, 2.5, 11.2, -75.0])
def test_the_delayed_model_is_the_cubic_through_its_four_nearest_samples_also_at_the_record_ends(late):
    """The sums the likelihood is made of, and the residuals least squares sees, against the delayed model built sample
    by sample here: the cubic through the four samples around k − late, or the four at the record's end beyond it (the
    compiled code takes the samples inside the record in a loop of their own and the ends in another)."""
    n = N
    signal, data = MODEL[0] / 3e-6, MODEL[1] / 50.0 + 1e-3 * RNG.standard_normal(N)
    value, slope = np.empty(n), np.empty(n)
    for k in range(n):
        first = min(max(k + int(np.floor(-late)), 1), n - 3)
        cubic = np.polynomial.Polynomial.fit(np.arange(first - 1, first + 3), signal[first - 1:first + 3], 3)
        value[k], slope[k] = cubic(k - late), cubic.deriv()(k - late)
    d = -slope
    r = data - value + late * d
    u = np.stack([np.ones(n), value, d])
    gram, projection, squares = sensors._moments(data[None], signal[None, None], np.array([[late]]))
    np.testing.assert_allclose(gram[0, 0], u @ u.T, rtol=1e-9, atol=1e-9 * n)
    np.testing.assert_allclose(projection[0, 0], u @ r, rtol=1e-9, atol=1e-9 * n)
    np.testing.assert_allclose(squares[0, 0], r @ r, rtol=1e-9)
    fitted = np.array([0.1, 0.02, 0.3])
    left = sensors._left(data[None], signal[None, None], np.array([[late]]), fitted[None, None])
    expected = data - fitted[0] - (1 + fitted[1]) * value - (late - fitted[2]) * slope
    np.testing.assert_allclose(left[0, 0], expected, rtol=1e-9, atol=1e-9)
    delayed = sensors._delayed(signal[None], np.array([late]))
    np.testing.assert_allclose(delayed[0][0], value, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(delayed[1][0], slope, rtol=1e-9, atol=1e-9)


def test_the_delay_is_integrated_out_as_quadrature_over_it_does():
    n, delay_sd = 1000, 0.5e-3
    t = np.arange(n) / FS

    def signal(at):  # a probe's two lines, known at any time
        return 3e-6 * np.sin(2 * np.pi * 50 * at + 0.3) + 1e-6 * np.sin(2 * np.pi * 150 * at) + 5e-7

    sigma = np.array([0.01 * np.std(signal(t))])
    delay = 1.7 / FS  # between samples
    data = (2e-8 + 1.003 * signal(t - delay) + sigma[0] * RNG.standard_normal(n))[None]
    instruments = sensors.Instruments.of({"b1_x": sensors.Sensor(5e-8, 0.01, delay_sd)}, ("b1_x",), FS)
    found = sensors.estimate(data, signal(t)[None], sigma, instruments)
    assert abs(found["delay"][0] - delay) < 4 * found["delay_sd"][0] and found["delay_sd"][0] < 0.01 / FS
    reported = sensors.summary(data, signal(t)[None], sigma, instruments, ("b1_x",), 0.94)["b1_x"]["delay"]
    assert reported["hdi"] == pytest.approx(reported["mean"] + np.array([-1.881, 1.881]) * reported["sd"], rel=1e-3)
    # The marginal over the delay by quadrature, offset and gain in closed form at each exactly delayed signal.
    exact_delay = sensors.Instruments(instruments.scale * [1.0, 1.0, 0.0], FS)
    grid = found["delay"][0] + found["delay_sd"][0] * np.linspace(-10, 10, 801)
    log_joint = np.array([sensors.log_likelihood(data, signal(t - d)[None], sigma, exact_delay) for d in grid])
    log_joint += stats.norm.logpdf(grid, scale=delay_sd)
    top = log_joint.max()
    marginal = top + np.log(np.trapezoid(np.exp(log_joint - top), grid))
    assert sensors.log_likelihood(data, signal(t)[None], sigma, instruments) == pytest.approx(marginal, abs=0.1)


def test_the_linearized_residual_and_design_are_the_likelihoods_normal_density():
    """What a regression beside the instruments takes (r and B about the delay's mode, :func:`sensors.linearized`): each
    channel's marginal likelihood is the Normal density of r with covariance σ²I + BBᵀ, delays, offsets and gains alike."""
    data = np.roll(readings(np.array([4e-8, 0.03]), np.array([1.01, 0.999])), 1, axis=1)  # a sample late
    instruments = sensors.Instruments(np.array([[5e-8, 0.01, 0.8], [0.02, 0.002, 0.6]]), FS)
    residual, design = sensors.linearized(data, MODEL, SIGMA, instruments)
    expected = [stats.multivariate_normal(np.zeros(N), SIGMA[c] ** 2 * np.eye(N) + design[c] @ design[c].T).logpdf(residual[c])
                for c in range(2)]
    assert sensors.log_likelihood(data, MODEL, SIGMA, instruments, per_channel=True) == pytest.approx(expected, rel=1e-9)
    residual, design = sensors.linearized(data, MODEL, SIGMA, None)
    assert np.array_equal(residual, data - MODEL) and design.shape == (2, N, 0)


@pytest.mark.parametrize("sds, flagged", [(0.8, []), (-3.0, []), (12.0, [(1, sensors.GAIN)])])
def test_an_instrument_far_outside_its_datasheet_is_out_of_spec(sds, flagged):
    """The speed sensor's gain ``sds`` datasheet sds off: out of spec when the data say so at prior odds e^-margin,
    and then its Bayes factor is the widened prior's gain in likelihood."""
    data = readings(np.zeros(2), np.array([1.0, 1.0 + sds * SCALE[1, 1]]))
    found = sensors.check(data, MODEL, SIGMA, INSTRUMENTS, margin=6.9)
    assert [(c, q) for c, q, _ in found.out_of_spec] == flagged
    if flagged:
        assert found.instruments.scale[1, sensors.GAIN] == SCALE[1, sensors.GAIN] * sensors.OUT_OF_SPEC
        # Alone widened, the Bayes factor is this channel's gain; it is then the whole gain of the check.
        assert found.out_of_spec[0][2] == pytest.approx(found.gain, rel=1e-9) and found.gain > 6.9
        # One gain's Normal evidence ratio in closed form: ½ĉ²(1/(1+v) − 1/(K²+v)) − ½ log((K²+v)/(1+v)), v = 1/λ
        # the data's variance of c, ĉ the least-squares estimate of c (in the datasheet sd's units).
        design = MODEL[1] * SCALE[1, 1]
        lam = design @ design / SIGMA[1] ** 2
        c_hat = design @ (data[1] - MODEL[1]) / SIGMA[1] ** 2 / lam
        v, k2 = 1 / lam, sensors.OUT_OF_SPEC**2
        assert found.gain == pytest.approx(0.5 * c_hat**2 * (1 / (1 + v) - 1 / (k2 + v)) - 0.5 * np.log((k2 + v) / (1 + v)), rel=1e-6)
        assert sensors.in_words("w1", "gain", 1.021, "rad/s") == "w1 reads 2.1 % high"
        assert sensors.in_words("b1_x", "delay", 4.2e-4, "m") == "b1_x lags by 0.42 ms"
        assert sensors.in_words("b1_x", "offset", -1.7e-8, "m") == "b1_x reads 1.7e-08 m low"
    else:
        assert found.instruments is INSTRUMENTS and found.gain == 0.0


def test_a_sensor_prior_must_be_a_finite_spread():
    with pytest.raises(ValueError, match="gain_sd must be a finite number >= 0"):
        sensors.Sensor(offset_sd=1e-8, gain_sd=-0.01)


def test_datasheet_offsets_and_delays_are_not_a_misfit_but_a_stiffer_shaft_still_is():
    from newdyn import hypotheses, model, noise, simulation

    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=500)
    channels = ("b1_x", "w1")
    healthy = hypotheses.Hypothesis("healthy", "healthy")
    instruments = sensors.Instruments.of({"b1_x": sensors.Sensor(offset_sd=5e-8, gain_sd=0.01, delay_sd=5e-4),
                                          "w1": sensors.Sensor(gain_sd=0.002, delay_sd=5e-4)}, channels, sampling.fs)

    def chi2(truth, offset=0.0, delay=0.0):
        late = model.Sampling(sampling.fs, sampling.t_first - delay, sampling.n_samples)  # the rig's state `delay` earlier
        clean = simulation.simulate(slots.complete(truth), late, channels)
        data, sigma = noise.add_noise(clean, channels, 40.0, 2)
        data[0] += offset * np.std(clean[0])
        return [hypotheses.fit(healthy, data, sigma, slots.complete({}), sampling, channels, instruments=s).chi2_red
                for s in (None, instruments)]

    exact, with_instruments = chi2({}, offset=0.2)
    assert exact > 10 and with_instruments < 1.1
    exact, with_instruments = chi2({}, delay=0.37e-3)  # time stamps late by less than two samples
    assert exact > 10 and with_instruments < 1.1
    # A delay takes the phase a resonance's shift gives the strongest line of a channel, not the rest of its change.
    exact, with_instruments = chi2({"kT3": 2.2e6})
    assert exact > 4 and with_instruments > 3


SUMS_IN_A_NEW_PROCESS = """
import sys
import numpy as np
from newdyn import sensors
rng = np.random.default_rng(5)
n = 2000
data = np.sin(np.linspace(0, 40, n))[None] * [[1.0], [3e-6]] + 1e-3 * rng.standard_normal((2, n))
model = data[None] * rng.uniform(0.9, 1.1, (40, 2, 1)) + 1e-3 * rng.standard_normal((40, 2, n))
sums = sensors._moments(data, model, rng.uniform(-3.0, 3.0, (40, 2)))
np.save(sys.argv[1], np.concatenate([s.ravel() for s in sums]))
print(sum(sensors._moments.stats.cache_hits.values()))
"""


def test_the_sums_loaded_from_numbas_cache_are_those_compiled_in_the_process(tmp_path):
    """A new checkout's first run compiles the likelihood's sums and later runs load them from numba's cache: both must
    give the same bits, or a rerun would not reproduce the first run's results."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    hits = {}
    for run in ("compiled", "cached"):
        done = subprocess.run([sys.executable, "-c", SUMS_IN_A_NEW_PROCESS, str(tmp_path / f"{run}.npy")], env=env,
                              capture_output=True, text=True, check=True)
        hits[run] = int(done.stdout.split()[-1])
    assert hits == {"compiled": 0, "cached": 1}
    np.testing.assert_array_equal(np.load(tmp_path / "compiled.npy"), np.load(tmp_path / "cached.npy"))
