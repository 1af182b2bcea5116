"""Measurement noise of rig.md: white Gaussian, independent per channel, set by an SNR.

σ_c = std(clean_c) · 10^(−SNR/20), the std over the recorded window with its mean removed.
Each channel draws from its own stream seeded by (seed, channel), so a channel's noise does not
change when other channels are added or removed, and a seed reproduces it exactly.

A measurement without a stated noise level gets σ from its own spectrum above a cut-off, where the
rig's clean signals have no content: no model enters, so model misfit cannot inflate or hide it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.signal

from . import model

WELCH_SEGMENT = 256  # samples per Welch segment for the noise floor: ~20 Hz bins at 5 kHz, many segments
MIN_FLOOR_BINS = 8


def noise_sigma(clean: np.ndarray, snr_db: float) -> np.ndarray:
    """Per-channel noise σ for ``clean`` (n_channels, n_samples) at ``snr_db``."""
    if not np.isfinite(snr_db):
        raise ValueError(f"SNR must be a finite number of dB (got {snr_db})")
    return np.std(clean, axis=-1) * 10.0 ** (-snr_db / 20.0)


def add_noise(clean: np.ndarray, channels: Sequence[str], snr_db: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Noisy copy of ``clean`` (n_channels, n_samples) and the σ used per channel."""
    sigma = noise_sigma(clean, snr_db)
    noise = np.stack(
        [np.random.default_rng([int(seed), model.CHANNELS.index(c)]).standard_normal(clean.shape[-1]) for c in channels]
    )
    return clean + sigma[:, None] * noise, sigma


def sigma_from_snr(y: np.ndarray, snr_db: float) -> np.ndarray:
    """Per-channel σ of a NOISY ``y`` (n_channels, n_samples) recorded at ``snr_db`` as :func:`noise_sigma`
    defines it: var(y) = var(clean) + σ² and σ² = var(clean)·10^(−SNR/10), so σ² = var(y)/(10^(SNR/10) + 1)."""
    if not np.isfinite(snr_db):
        raise ValueError(f"SNR must be a finite number of dB (got {snr_db})")
    return np.sqrt(np.var(y, axis=-1) / (10.0 ** (snr_db / 10.0) + 1.0))


def noise_floor_sigma(y: np.ndarray, fs: float, band_low_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """White-noise σ per channel of ``y`` (n_channels, n_samples) from its spectrum at and above
    ``band_low_hz`` [Hz], and the standard error of that σ (both in the channel's unit).

    σ̂² = (fs/2) · mean of the one-sided Welch PSD (Hann, linear detrend, 50 % overlap) over the bins
    from ``band_low_hz`` up to but without the Nyquist bin, whose one-sided density is only σ²/fs.
    The standard error is exact for Gaussian white noise: σ̂² is a quadratic form of the samples, so
    its variance follows from the covariances of the windowed DFT coefficients (:func:`_floor_relative_variance`).
    """
    y = np.atleast_2d(np.asarray(y, dtype=float))
    band = floor_band(y.shape[-1], fs, band_low_hz)
    nperseg = min(WELCH_SEGMENT, y.shape[-1])
    _, density = scipy.signal.welch(y, fs=fs, window="hann", nperseg=nperseg, noverlap=nperseg // 2, detrend="linear", axis=-1)
    sigma = np.sqrt(np.mean(density[:, band], axis=-1) * fs / 2)
    # σ̂ = sqrt(σ̂²): its relative error is half that of σ̂².
    relative_se = 0.5 * np.sqrt(_floor_relative_variance(y.shape[-1], nperseg, np.flatnonzero(band)))
    return sigma, relative_se * sigma


def floor_band(n_samples: int, fs: float, band_low_hz: float) -> np.ndarray:
    """Which Welch bins of a record of ``n_samples`` at ``fs`` [Hz] :func:`noise_floor_sigma` averages:
    from ``band_low_hz`` up to but without Nyquist.  ValueError when they are too few to read σ from."""
    nperseg = min(WELCH_SEGMENT, n_samples)
    frequency = np.fft.rfftfreq(nperseg, 1.0 / fs)
    band = (frequency >= band_low_hz) & (frequency < fs / 2)
    if band_low_hz >= fs / 2:
        raise ValueError(f"noise band from {band_low_hz:g} Hz is empty: it must start below Nyquist ({fs / 2:g} Hz)")
    if band.sum() < MIN_FLOOR_BINS:
        raise ValueError(
            f"noise band from {band_low_hz:g} Hz to Nyquist ({fs / 2:g} Hz) holds {band.sum()} Welch bins of "
            f"{fs / nperseg:.3g} Hz, fewer than {MIN_FLOOR_BINS}: lower band_low_hz or record longer"
        )
    return band


def _floor_relative_variance(n_samples: int, nperseg: int, bins: np.ndarray) -> float:
    """Var(σ̂²)/σ⁴ of :func:`noise_floor_sigma` for Gaussian white noise of σ (its equivalent degrees of
    freedom are 2 over this).

    One segment's DFT coefficients in the band are X = A·x with A the DFT rows of window · detrend.
    For real Gaussian x, cov(|X_i|², |X_j|²) = |E X_i X_j*|² + |E X_i X_j|², and segments s and s+j
    share samples through A's overlapping columns; summing these over all segment pairs is exact.
    """
    step = nperseg - nperseg // 2
    n_segments = (n_samples - nperseg) // step + 1
    window = scipy.signal.get_window("hann", nperseg)
    A = np.fft.rfft(window[:, None] * scipy.signal.detrend(np.eye(nperseg), axis=0, type="linear"), axis=0)[bins]
    mean = n_segments * np.sum(np.abs(A) ** 2)  # E of Σ|X|² over segments and bins, in units of σ²
    variance = n_segments * _pair_covariance(A, A)
    for lag in range(1, n_segments):
        shift = lag * step
        if shift >= nperseg:
            break
        variance += 2 * (n_segments - lag) * _pair_covariance(A[:, shift:], A[:, : nperseg - shift])
    return variance / mean**2


def _pair_covariance(a: np.ndarray, b: np.ndarray) -> float:
    """Σ_ij cov(|X_i|², |Y_j|²)/σ⁴ for X = a·x and Y = b·x over the same unit white samples x."""
    return float(np.sum(np.abs(a @ b.conj().T) ** 2) + np.sum(np.abs(a @ b.T) ** 2))


def at_measured_snr(data: np.ndarray, sigma: np.ndarray, signals: np.ndarray) -> tuple[float, np.ndarray]:
    """(the measured channels' mean SNR [dB], the noise σ of ``signals`` (channel, time) at that SNR): what
    an unmeasured channel would show, measured as well as the others."""
    snr_db = float(np.mean(20 * np.log10(np.sqrt(np.maximum(np.var(data, axis=-1) - sigma**2, 0)) / sigma)))
    return snr_db, np.std(signals, axis=-1) * 10 ** (-snr_db / 20)
