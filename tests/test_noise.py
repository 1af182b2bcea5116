"""Noise injection against rig.md: σ per channel from the SNR, seeded, independent per channel."""

import numpy as np
import pytest

from newdyn import model
from newdyn.noise import add_noise, noise_sigma
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
