"""Measurement noise of rig.md: white Gaussian, independent per channel, set by an SNR.

σ_c = std(clean_c) · 10^(−SNR/20), the std over the recorded window with its mean removed.
Each channel draws from its own stream seeded by (seed, channel), so a channel's noise does not
change when other channels are added or removed, and a seed reproduces it exactly.

A measurement without a stated noise level gets σ from its own spectrum above a cut-off, where the
rig's clean signals have no content: no model enters, so model misfit cannot inflate or hide it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy  # scipy.signal and scipy.ndimage load on first use: adding noise needs neither

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
            f"{fs / nperseg:.3g} Hz, fewer than {MIN_FLOOR_BINS}: a band starting lower or a higher sampling rate holds more"
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


LINE_WINDOW = "blackmanharris"  # sidelobes below −92 dB: a misfit line 60 dB above the noise leaks nothing into it
LINE_HALF_WIDTH = 4  # bins either side of a line that its window's main lobe covers
MEDIAN_HALF_WIDTH = 32  # bins either side of a bin in the running median the noise's spectrum is read from
BIN_STRIDE = 3  # bins apart that the window leaves uncorrelated, the ones the Whittle likelihood counts
LINE_FALSE_ALARM = 0.01  # probability that a record of pure noise has a bin flagged as a line
LINE_PASSES = 3


@dataclass(frozen=True)
class Colour:
    """Per-channel autoregressive noise: e_k = x_k − Σ_j a_j x_{k−j} is white, of σ_e = innovation·σ_x.

    White noise is the special case without coefficients (``ar`` of shape (C, 0), innovation 1)."""

    ar: np.ndarray  # (channel, order) coefficients a_j, zero beyond a channel's own order
    innovation: np.ndarray  # (channel,) σ_e/σ_x

    @property
    def order(self) -> int:
        return self.ar.shape[1]

    @property
    def white(self) -> bool:
        return not np.any(self.ar)

    def whiten(self, x: np.ndarray) -> np.ndarray:
        """e_k for k ≥ order of ``x`` (..., C, n): the first ``order`` samples only start the filter."""
        x = np.asarray(x, dtype=float)
        e = x[..., self.order:].copy()
        for j in range(1, self.order + 1):
            e -= self.ar[:, j - 1, None] * x[..., self.order - j: x.shape[-1] - j]
        return e

    def seen(self, x: np.ndarray, sigma: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """How a likelihood sees ``x`` (..., C, n), noise of level ``sigma`` (C,) at ``times`` (n,): whitened, the
        innovation's σ, and the times of the samples it keeps."""
        return self.whiten(x), sigma * self.innovation, times[self.order:]

    def summary(self, channels: Sequence[str]) -> dict[str, dict]:
        """``{channel: {ar, innovation}}`` of the coloured channels, as ``verdict.json`` reports them."""
        return {c: {"ar": a[: np.max(np.flatnonzero(a), initial=-1) + 1].tolist(), "innovation": float(r)}
                for c, a, r in zip(channels, self.ar, self.innovation) if np.any(a)}

    @classmethod
    def from_summary(cls, summary: Mapping[str, Mapping], channels: Sequence[str]) -> Colour:
        """The colour a :meth:`summary` describes, over ``channels`` (those not in it white)."""
        order = max((len(s["ar"]) for s in summary.values()), default=0)
        ar = np.zeros((len(channels), order))
        for i, c in enumerate(channels):
            ar[i, : len(summary.get(c, {}).get("ar", []))] = summary.get(c, {}).get("ar", [])
        return cls(ar, np.array([float(summary.get(c, {}).get("innovation", 1.0)) for c in channels]))


def white(n_channels: int) -> Colour:
    return Colour(np.zeros((n_channels, 0)), np.ones(n_channels))


def colour(residual: np.ndarray, max_order: int, margin: float = 0.0) -> tuple[Colour, np.ndarray]:
    """The noise colour of ``residual`` (C, n), a measurement less a model of it, per channel: the AR order
    ≤ ``max_order`` that the Bayesian information criterion picks (often 0: white), at prior odds e^−``margin``
    against any colour (its BIC must beat white noise's by 2·margin), its Yule–Walker coefficients; and the
    noise's σ, the level of that broadband part (C,).

    A model's misfit is the machine's periodic response, lines in the spectrum, while the noise is broadband:
    the spectrum is read through a window that keeps lines to their own few bins, bins that stand out of the
    running median as no noise could are left out, and the AR spectra are scored by the Whittle likelihood
    of the remaining bins, every :data:`BIN_STRIDE`-th one, as the window correlates neighbours."""
    residual = np.atleast_2d(np.asarray(residual, dtype=float))
    fitted = [_channel_colour(x, max_order, margin) for x in residual]
    order = max([len(a) for a, _, _ in fitted], default=0)
    ar = np.zeros((len(fitted), order))
    for c, (a, _, _) in enumerate(fitted):
        ar[c, :len(a)] = a
    return Colour(ar, np.array([ratio for _, ratio, _ in fitted])), np.array([level for _, _, level in fitted])


def _channel_colour(x: np.ndarray, max_order: int, margin: float) -> tuple[np.ndarray, float, float]:
    """(AR coefficients, σ_e/σ_x, σ_x) of one channel's residual."""
    n = x.size
    window = scipy.signal.get_window(LINE_WINDOW, n)
    periodogram = np.abs(np.fft.rfft((x - x.mean()) * window)) ** 2 / np.sum(window**2)  # two-sided density, unit fs
    inside = np.arange(1 + LINE_HALF_WIDTH, periodogram.size - 1)  # off DC (the mean's leakage) and Nyquist
    threshold = math.log(inside.size / LINE_FALSE_ALARM)  # an exponential bin exceeds its mean this much this rarely
    outside = np.ones(periodogram.size, dtype=bool)
    outside[inside] = False
    line = outside
    for _ in range(LINE_PASSES):  # lines found raise the median around them: read it again without them
        level = _running_median(np.where(line, np.nan, periodogram)) / math.log(2)
        found = np.zeros(periodogram.size, dtype=bool)
        found[inside[periodogram[inside] > threshold * level[inside]]] = True
        line = scipy.ndimage.binary_dilation(found, iterations=LINE_HALF_WIDTH) | outside
    noise_only = np.where(line, level, periodogram)  # the lines' bins at the noise level around them
    full = np.concatenate([noise_only, noise_only[-2:0:-1]]) if n % 2 == 0 else np.concatenate([noise_only, noise_only[:0:-1]])
    covariance = np.fft.ifft(full).real[: max_order + 1]
    kept = np.flatnonzero(~line)[::BIN_STRIDE]
    best, best_bic = None, math.inf
    for order, (a, variance) in enumerate(_levinson(covariance, max_order)):
        gain = np.abs(1.0 - np.exp(-2j * np.pi * np.outer(kept / n, np.arange(1, order + 1))) @ a) ** 2  # |A(f)|²
        innovation = float(np.mean(periodogram[kept] * gain))  # the Whittle likelihood's maximum over σ_e² given a
        whittle = -kept.size * (math.log(innovation) + 1.0) + float(np.sum(np.log(gain)))
        bic = -2.0 * whittle + order * math.log(kept.size) + (2.0 * margin if order else 0.0)
        if bic < best_bic:
            # σ_e/σ_x of the AR model itself, Π(1 − k²) over its reflection coefficients, and σ_e from the bins
            # kept: the level of the lowest frequencies, where few cycles fit and lines crowd, does not enter
            ratio = math.sqrt(variance / covariance[0])
            best, best_bic = (a, ratio, math.sqrt(innovation) / ratio), bic
    return best


def _running_median(values: np.ndarray) -> np.ndarray:
    """The median of the finite ``values`` within :data:`MEDIAN_HALF_WIDTH` bins of each bin."""
    padded = np.pad(values, MEDIAN_HALF_WIDTH, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * MEDIAN_HALF_WIDTH + 1)
    empty = np.all(np.isnan(windows), axis=-1)  # inside a run of lines wider than the window
    median = np.full(values.size, np.nanmedian(values))
    median[~empty] = np.nanmedian(windows[~empty], axis=-1)
    return median


def _levinson(covariance: np.ndarray, max_order: int):
    """(a, innovation variance) of the Yule–Walker AR fits of orders 0 … ``max_order`` to ``covariance``."""
    a, variance = np.zeros(0), float(covariance[0])
    yield a, variance
    for order in range(1, max_order + 1):
        reflection = (covariance[order] - a @ covariance[order - 1:0:-1]) / variance
        a = np.concatenate([a - reflection * a[::-1], [reflection]])
        variance *= 1.0 - reflection**2
        yield a, variance
