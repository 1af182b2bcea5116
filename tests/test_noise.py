"""Noise injection against rig.md: σ per channel from the SNR, seeded, independent per channel; and σ
recovered from a noisy record alone, by its noise floor or by its stated SNR."""

import math

import numpy as np
import pytest
import scipy.signal

from newdyn import faults, model
from newdyn.noise import Colour, add_noise, colour, noise_floor_sigma, noise_sigma, sigma_from_snr
from newdyn.simulation import simulate

CHANNELS = ["b1_x", "w1", "torque_c"]


@pytest.fixture(scope="module")
def clean():
    return simulate({}, model.Sampling(), CHANNELS)


@pytest.mark.parametrize("snr_db", [40.0, 20.0, 0.0])
def test_noise_has_the_requested_sigma(clean, snr_db):
    noisy, sigma = add_noise(clean, CHANNELS, snr_db, seed=3)
    expected = np.std(clean - clean.mean(axis=1, keepdims=True), axis=1) * 10 ** (-snr_db / 20)
    np.testing.assert_allclose(sigma, expected, rtol=1e-12)
    # The sample std of 5000 Gaussian draws is within 3 standard errors (σ/√(2n)) of σ.
    drawn = np.std(noisy - clean, axis=1, ddof=1)
    assert np.all(np.abs(drawn / sigma - 1) < 3 / np.sqrt(2 * clean.shape[1]))
    # White: no lag-1 correlation beyond chance.
    e = (noisy - clean) / sigma[:, None]
    assert np.all(np.abs(np.mean(e[:, 1:] * e[:, :-1], axis=1)) < 4 / np.sqrt(clean.shape[1]))


def test_same_seed_same_noise_other_seed_other_noise(clean):
    a, _ = add_noise(clean, CHANNELS, 40.0, seed=7)
    b, _ = add_noise(clean, CHANNELS, 40.0, seed=7)
    c, _ = add_noise(clean, CHANNELS, 40.0, seed=8)
    np.testing.assert_array_equal(a, b)
    assert np.all(np.abs(np.corrcoef((a - clean)[1], (c - clean)[1])[0, 1]) < 0.05)


def test_a_channels_noise_does_not_depend_on_the_other_channels(clean):
    all_three, _ = add_noise(clean, CHANNELS, 40.0, seed=1)
    alone, _ = add_noise(clean[1:2], CHANNELS[1:2], 40.0, seed=1)
    np.testing.assert_array_equal(all_three[1], alone[0])
    assert abs(np.corrcoef(all_three[0] - clean[0], all_three[1] - clean[1])[0, 1]) < 0.05


def test_non_finite_snr_is_refused(clean):
    with pytest.raises(ValueError, match="finite"):
        noise_sigma(clean, float("inf"))


FS = model.Sampling().fs
FLOOR_HZ = 1000.0  # the rig's clean signals have no content above ~1 kHz


def test_noise_floor_of_white_noise_is_sigma_with_an_honest_standard_error():
    sigma = 0.05
    # 200 independent records, one per seed, estimated at once as 200 channels.
    y = sigma * np.stack([np.random.default_rng(seed).standard_normal(5000) for seed in range(200)])
    estimate, se = noise_floor_sigma(y, FS, FLOOR_HZ)
    z = (estimate - sigma) / se
    assert abs(z[0]) < 3
    # The z-scores are standard: mean within 4 standard errors of 0, sd within ±20 % of 1.
    assert abs(z.mean()) < 4 / np.sqrt(z.size)
    assert 0.8 < z.std() < 1.2


def test_noise_floor_standard_error_shrinks_as_one_over_root_n():
    _, se_short = noise_floor_sigma(np.random.default_rng(0).standard_normal((1, 5000)), FS, FLOOR_HZ)
    _, se_long = noise_floor_sigma(np.random.default_rng(0).standard_normal((1, 20000)), FS, FLOOR_HZ)
    # Segments of 256 overlap by half in both, so the equivalent degrees of freedom scale with the
    # segment count: (5000 − 128) // 128 = 38 and (20000 − 128) // 128 = 155.
    assert se_short / se_long == pytest.approx(np.sqrt(155 / 38), rel=0.01)


STICK_SLIP = faults.scenario_values({"fault": {"kind": "stick_slip", "parameters": {"T_max": 1854.95, "r_k": 1.0}}}, model.DEFAULTS)


@pytest.mark.parametrize("snr_db", [40.0, 20.0])
@pytest.mark.parametrize("values", [{}, STICK_SLIP], ids=["healthy", "stick_slip"])
def test_noise_floor_of_the_rig_is_its_noise_sigma(snr_db, values):
    clean = simulate(values, model.Sampling(), CHANNELS)
    for seed in range(3):
        noisy, sigma = add_noise(clean, CHANNELS, snr_db, seed)
        estimate, se = noise_floor_sigma(noisy, FS, FLOOR_HZ)
        assert np.all(np.abs(estimate - sigma) < 3 * se), (seed, (estimate - sigma) / se)


def test_noise_floor_refuses_an_empty_or_thin_band():
    y = np.random.default_rng(0).standard_normal((1, 5000))
    with pytest.raises(ValueError, match="empty"):
        noise_floor_sigma(y, FS, FS / 2)
    with pytest.raises(ValueError, match="fewer than 8"):
        noise_floor_sigma(y, FS, FS / 2 - 100.0)


@pytest.mark.parametrize("snr_db", [40.0, 20.0, 0.0])
def test_sigma_from_snr_recovers_noise_sigma(clean, snr_db):
    noisy, sigma = add_noise(clean, CHANNELS, snr_db, seed=3)
    # var(y) = var(clean)(1 + q) + 2 cov(clean, noise) + (sample var(noise) − σ²), q = 10^(−SNR/10):
    # relative sampling error of var(y) is √(2q²/n + 4q/n)/(1 + q), and half that for σ.
    q, n = 10 ** (-snr_db / 10), clean.shape[1]
    se = 0.5 * np.sqrt(2 * q**2 / n + 4 * q / n) / (1 + q)
    assert np.all(np.abs(sigma_from_snr(noisy, snr_db) / sigma - 1) < 3 * se)


def _ar1(phi: float, shape, seed: int) -> np.ndarray:
    """Unit-variance AR(1) noise from scipy's filter: a generator the estimator does not share."""
    white = np.random.default_rng(seed).standard_normal(shape)
    return scipy.signal.lfilter([1.0], [1.0, -phi], white, axis=-1) * np.sqrt(1.0 - phi**2)


def _lines(n: int, fs: float, amplitude: float) -> np.ndarray:
    """A rotating machine's misfit: harmonics of 12.3 Hz and two resonances, far above the noise."""
    t = np.arange(n) / fs
    return sum(amplitude * np.sin(2 * np.pi * f * t + f) for f in (12.3, 24.6, 36.9, 49.2, 150.2, 611.1))


def test_white_noise_is_found_white_through_misfit_lines():
    n, fs = 5000, 5000.0
    rng = np.random.default_rng(11)
    # at the diagnosis's prior odds against colour, e^−6.9
    found = [colour(rng.standard_normal((2, n)) + _lines(n, fs, 100.0 * (seed % 2)), 8, math.log(1000))[0] for seed in range(20)]
    assert all(c.white for c in found)
    assert all(c.innovation.tolist() == [1.0, 1.0] for c in found if c.white)


@pytest.mark.parametrize("phi", [0.5, 0.9, 0.97])
def test_ar1_noise_is_found_beneath_misfit_lines(phi):
    n, fs = 5000, 5000.0
    x = _ar1(phi, (1, n), seed=int(phi * 100)) + _lines(n, fs, 100.0)
    found, level = colour(x, 8)
    assert found.order >= 1
    # the fitted spectrum, not the coefficients, is what whitening needs: compare it where the noise lives
    frequency = np.linspace(5.0, 2000.0, 200)
    truth = (1 - phi**2) / np.abs(1 - phi * np.exp(-2j * np.pi * frequency / fs)) ** 2
    response = 1.0 - np.exp(-2j * np.pi * np.outer(frequency / fs, np.arange(1, found.order + 1))) @ found.ar[0]
    ratio = found.innovation[0] ** 2 / np.abs(response) ** 2 / truth
    assert np.all(np.abs(np.log(ratio)) < 0.35), ratio.min()
    assert abs(found.innovation[0] - np.sqrt(1 - phi**2)) < 0.25 * np.sqrt(1 - phi**2)
    assert level[0] == pytest.approx(1.0, rel=0.3)


def test_whitening_an_ar_process_leaves_white_noise():
    coefficients = np.array([[1.2, -0.5], [0.6, 0.0]])
    white = np.random.default_rng(5).standard_normal((2, 4000))
    x = np.stack([scipy.signal.lfilter([1.0], np.r_[1.0, -a], w) for a, w in zip(coefficients, white)])
    e = Colour(coefficients, np.ones(2)).whiten(x)
    np.testing.assert_allclose(e, white[:, 2:], atol=1e-12)
