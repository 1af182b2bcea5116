"""Measurement noise of rig.md: white Gaussian, independent per channel, set by an SNR.

σ_c = std(clean_c) · 10^(−SNR/20), the std over the recorded window with its mean removed.
Each channel draws from its own stream seeded by (seed, channel), so a channel's noise does not
change when other channels are added or removed, and a seed reproduces it exactly.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from . import model


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
