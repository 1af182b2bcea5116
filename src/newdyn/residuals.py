"""Where a model fails: the residual r = data − model against white noise of known σ, by frequency
band, by load-cycle phase and as a time-frequency map.

Every statistic is normalized by σ so that "residual = white Gaussian noise of σ" (the null) has a
known exact distribution: sums of squared normalized periodogram bins or samples are chi-square.
:func:`where_it_fails` tests all bands and phase bins of all channels at once and, by Bonferroni,
raises a false alarm on pure noise with probability at most ``alpha``.  σ is taken as exact: an
estimated σ (e.g. :func:`newdyn.noise.noise_floor_sigma`, 1.3 % on 1 s at 5 kHz) scales every excess
by (σ/σ̂)², an error as large as a band's own chance spread √(2/dof) only from ~2700 dof on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import scipy  # scipy.signal and scipy.stats load on first use

# [Hz]: octaves from the rotation (≈ 24.7 Hz) and load harmonics (12 Hz up to ~72 Hz) up to Nyquist.
DEFAULT_BANDS: tuple[tuple[float, float], ...] = (
    (0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0), (80.0, 160.0), (160.0, 320.0), (320.0, 640.0),
    (640.0, 1280.0), (1280.0, math.inf),
)
PHASE_BINS = 24
MAP_SEGMENT = 256  # samples per spectrogram segment: ~20 Hz by ~50 ms at 5 kHz


class BandExcess(NamedTuple):
    bands: np.ndarray  # (n_bands, 2) [Hz], the upper edge clipped to Nyquist
    excess: np.ndarray  # (n_channels, n_bands) observed / white-noise power
    p_value: np.ndarray  # (n_channels, n_bands) chi-square upper tail
    dof: np.ndarray  # (n_bands,) chi-square degrees of freedom of each band under the null


class PhaseExcess(NamedTuple):
    edges: np.ndarray  # (n_bins + 1,) load-cycle phase, 0 … 1
    excess: np.ndarray  # (n_channels, n_bins) mean (r/σ)²
    p_value: np.ndarray  # (n_channels, n_bins) chi-square upper tail
    counts: np.ndarray  # (n_bins,) samples per bin: the chi-square degrees of freedom under the null


def spectral_excess(
    residual: np.ndarray, sigma: np.ndarray, fs: float, bands: Sequence[tuple[float, float]] | None = None
) -> BandExcess:
    """Residual power per frequency band relative to white noise of ``sigma``.

    ``residual`` (n_channels, n_samples) and ``sigma`` (n_channels,) in the channel's unit, ``fs`` and
    ``bands`` (low, high) in Hz, each holding low ≤ f < high (the band reaching Nyquist holds it too).
    The default bands are :data:`DEFAULT_BANDS` that start below Nyquist.  With P_k = |DFT_k(r/σ)|²/n,
    white noise gives independent 2·P_k ~ χ²₂ for 0 < f < Nyquist and P_k ~ χ²₁ at 0 and Nyquist; the
    band's T = Σ d_k P_k (d_k its dof) is χ² with Σ d_k dof, and its excess is T / Σ d_k (mean 1).
    """
    z = _normalized(residual, sigma)
    n = z.shape[-1]
    frequency = np.fft.rfftfreq(n, 1.0 / fs)
    power = np.abs(np.fft.rfft(z, axis=-1)) ** 2 / n
    bin_dof = np.full(frequency.size, 2.0)
    bin_dof[0] = 1.0
    if n % 2 == 0:
        bin_dof[-1] = 1.0  # the Nyquist bin is real
    nyquist = fs / 2
    if bands is None:
        bands = [band for band in DEFAULT_BANDS if band[0] < nyquist]
    edges = np.array([(low, min(high, nyquist)) for low, high in bands], dtype=float).reshape(-1, 2)
    members = (frequency >= edges[:, :1]) & ((frequency < edges[:, 1:]) | (edges[:, 1:] >= nyquist))
    empty = ~members.any(axis=1)
    if empty.any():
        raise ValueError(f"bands {edges[empty].tolist()} Hz hold no frequency bin of {fs / n:.3g} Hz up to {nyquist:g} Hz")
    dof = members @ bin_dof
    statistic = (power * bin_dof) @ members.T
    return BandExcess(edges, statistic / dof, scipy.stats.chi2.sf(statistic, dof), dof)


def load_phase(times: np.ndarray, load_freq: float) -> np.ndarray:
    """Load-cycle phase (t·f_l) mod 1 of rig-clock ``times`` [s] for load pulsation ``load_freq`` [Hz]."""
    return np.mod(np.asarray(times, dtype=float) * load_freq, 1.0)


def phase_excess(
    residual: np.ndarray, sigma: np.ndarray, times: np.ndarray, load_freq: float, n_bins: int = PHASE_BINS
) -> PhaseExcess:
    """Mean (r/σ)² per load-cycle phase bin; under the null each bin's sum is χ² with one dof per sample.

    ``times`` [s] are the rig clock of the samples, ``load_freq`` [Hz] the load's base frequency.
    A residual correlated in time (a wrong model) is no concern: the null is white noise.
    """
    z = _normalized(residual, sigma)
    index = np.minimum((load_phase(times, load_freq) * n_bins).astype(int), n_bins - 1)
    counts = np.bincount(index, minlength=n_bins)
    if np.any(counts == 0):
        raise ValueError(f"{np.sum(counts == 0)} of {n_bins} load-phase bins hold no sample: the record is too short")
    statistic = np.stack([np.bincount(index, weights=row**2, minlength=n_bins) for row in z])
    return PhaseExcess(np.linspace(0.0, 1.0, n_bins + 1), statistic / counts, scipy.stats.chi2.sf(statistic, counts), counts)


def phase_null_band(counts: np.ndarray, coverage: float = 0.999) -> tuple[np.ndarray, np.ndarray]:
    """Central ``coverage`` interval of a phase bin's excess under the null, χ²(N)/N for N = ``counts``."""
    tail = (1.0 - coverage) / 2
    return scipy.stats.chi2.ppf(tail, counts) / counts, scipy.stats.chi2.isf(tail, counts) / counts


def time_frequency_map(
    residual: np.ndarray, sigma: np.ndarray, fs: float, nperseg: int = MAP_SEGMENT, t_first: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spectrogram of r/σ in units of the white-noise floor: frequencies [Hz], segment centre times [s]
    (offset by ``t_first``, the time of the first sample) and the map (n_channels, n_freq, n_times).

    Hann segments with half overlap and no detrending: white noise of σ gives expectation exactly 1 in
    every cell, each cell χ²₂/2 (χ²₁ at 0 Hz and Nyquist); cells next in time or frequency correlate.
    """
    z = _normalized(residual, sigma)
    nperseg = min(nperseg, z.shape[-1])
    frequency, segment_times, density = scipy.signal.spectrogram(
        z, fs=fs, window="hann", nperseg=nperseg, noverlap=nperseg // 2, detrend=False, scaling="density", axis=-1
    )
    # The one-sided density of unit white noise is 2/fs, but 1/fs at 0 Hz and (even segments) Nyquist.
    floor = np.full(frequency.size, 2.0 / fs)
    floor[0] = 1.0 / fs
    if nperseg % 2 == 0:
        floor[-1] = 1.0 / fs
    return frequency, segment_times + t_first, density / floor[:, None]


def where_it_fails(
    residual: np.ndarray,
    sigma: np.ndarray,
    channels: Sequence[str],
    times: np.ndarray,
    fs: float,
    load_freq: float,
    alpha: float = 1e-3,
    bands: Sequence[tuple[float, float]] | None = None,
    n_bins: int = PHASE_BINS,
) -> list[dict]:
    """Frequency bands and load-phase windows where the residual stands above the noise floor, as
    JSON-ready dicts sorted by excess (observed / white-noise power), largest first; [] when the
    residual is consistent with white noise of ``sigma``.

    All band and phase-bin tests of all channels are one family: each is flagged at p < alpha / m
    (Bonferroni over its m tests), so pure noise gives a non-empty list with probability ≤ ``alpha``.
    Adjacent flagged phase bins, also across phase 1 → 0, merge into one window (``phase_high`` may
    then exceed 1) whose excess and p-value are recomputed from the merged samples.
    """
    spectral = spectral_excess(residual, sigma, fs, bands)
    phase = phase_excess(residual, sigma, times, load_freq, n_bins)
    threshold = alpha / (len(channels) * (len(spectral.bands) + n_bins))
    findings = []
    for c, channel in enumerate(channels):
        for (low, high), excess, p_value in zip(spectral.bands, spectral.excess[c], spectral.p_value[c]):
            if p_value < threshold:
                findings.append(
                    {"channel": channel, "kind": "band", "low_hz": float(low), "high_hz": float(high),
                     "excess": float(excess), "p_value": float(p_value)}
                )
        for first, last in _runs(phase.p_value[c] < threshold):
            members = np.arange(first, last + 1) % n_bins
            dof = phase.counts[members].sum()
            statistic = np.sum(phase.excess[c, members] * phase.counts[members])
            findings.append(
                {"channel": channel, "kind": "phase", "phase_low": first / n_bins, "phase_high": (last + 1) / n_bins,
                 "excess": float(statistic / dof), "p_value": float(scipy.stats.chi2.sf(statistic, dof))}
            )
    return sorted(findings, key=lambda finding: -finding["excess"])


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) indices of the runs of True in a circular array; last may exceed the length when
    a run wraps from the end to the start.  A circle of all True is one run 0 … n−1."""
    n = flags.size
    if flags.all():
        return [(0, n - 1)]
    start = int(np.argmin(flags))  # a False: no run crosses it, so the circle unrolls from there
    steps = np.diff(np.concatenate(([0], np.roll(flags, -start).astype(int), [0])))
    runs = []
    for first, last in zip(np.flatnonzero(steps == 1), np.flatnonzero(steps == -1) - 1):
        offset = start if first + start < n else start - n
        runs.append((int(first + offset), int(last + offset)))
    return runs


def _normalized(residual: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """r/σ as (n_channels, n_samples); σ must be positive and finite."""
    residual = np.atleast_2d(np.asarray(residual, dtype=float))
    sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
    if sigma.shape != residual.shape[:1]:
        raise ValueError(f"sigma {sigma.shape} must hold one value per channel of residual {residual.shape}")
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(f"sigma must be positive and finite (got {sigma})")
    return residual / sigma[:, None]
