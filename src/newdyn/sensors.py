"""Instrument nuisances of a channel, marginalized in closed form: an offset and a gain error.

A channel reads y(t) = o + g·m(t) + e(t): the model's output m through an instrument whose offset o and
gain g are known only to a datasheet's accuracy, o ~ N(0, s_o²) and g ~ N(1, s_g²), and white noise
e ~ N(0, σ²).  Both enter linearly, so they integrate out exactly: with the residual r = y − m and the
design B = [s_o·1, s_g·m] (n × 2, the prior's scales folded in), r ~ N(0, σ² I + B Bᵀ), and

    rᵀ (σ² I + B Bᵀ)⁻¹ r = (‖r − B ĉ‖² + σ² ‖ĉ‖²) / σ²,   ĉ = (BᵀB + σ² I)⁻¹ Bᵀ r,
    log |σ² I + B Bᵀ| = n log σ² + log |I + BᵀB / σ²|,

ĉ being the posterior mean of (o/s_o, (g − 1)/s_g).  The first line is a sum of squares, n + 2 of them per
channel: what least squares minimizes.  A scale of zero fits nothing (its column drops out); with both zero this
is the plain Gaussian likelihood.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Sensor:
    """The prior spread of one channel's instrument errors: offset in the channel's unit, gain relative."""

    offset_sd: float = 0.0
    gain_sd: float = 0.0

    def __post_init__(self):
        for name in ("offset_sd", "gain_sd"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


def scales(sensors: Mapping[str, Sensor], channels: Sequence[str]) -> np.ndarray:
    """(channel, 2) prior scales (s_o, s_g) of ``channels``; a channel without a sensor model has none."""
    none = Sensor()
    return np.array([[sensors.get(c, none).offset_sd, sensors.get(c, none).gain_sd] for c in channels], dtype=float)


def _integrated(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray):
    """(z (..., C, n + 2), ĉ (..., C, 2), BᵀB/σ² + I (..., C, 2, 2)): the misfit left after the most probable
    offset and gain in σ followed by those two in their prior's sd, whose squares sum to rᵀC⁻¹r, and the rest.
    B's columns are s_o·1 and s_g·m, so its Gram matrix and Bᵀr take sums over time only."""
    residual = data - model
    s_o, s_g, variance = scale[:, 0, None], scale[:, 1, None], (sigma**2)[..., None]
    n = model.shape[-1]
    sum_m, sum_mm = model.sum(axis=-1), np.einsum("...n,...n->...", model, model)
    g00 = 1.0 + n * s_o[..., 0] ** 2 / variance[..., 0]
    g01 = s_o[..., 0] * s_g[..., 0] * sum_m / variance[..., 0]
    g11 = 1.0 + s_g[..., 0] ** 2 * sum_mm / variance[..., 0]
    g00 = np.broadcast_to(g00, g11.shape)  # the offset's term has no model in it
    p0 = s_o[..., 0] * residual.sum(axis=-1) / variance[..., 0]
    p1 = s_g[..., 0] * np.einsum("...n,...n->...", model, residual) / variance[..., 0]
    det = g00 * g11 - g01**2
    c_hat = np.stack([(g11 * p0 - g01 * p1) / det, (g00 * p1 - g01 * p0) / det], axis=-1)
    left = (residual - s_o * c_hat[..., :1] - s_g * model * c_hat[..., 1:]) / np.sqrt(variance)
    gram = np.stack([np.stack([g00, g01], axis=-1), np.stack([g01, g11], axis=-1)], axis=-2)
    return np.concatenate([left, c_hat], axis=-1), c_hat, gram


def standardized_residuals(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., C, n + 2) numbers whose squares sum to each channel's rᵀC⁻¹r: what least squares minimizes."""
    return _integrated(data, model, sigma, scale)[0]


def log_likelihood(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray, per_channel: bool = False) -> np.ndarray:
    """log p(y | m) with each channel's offset and gain integrated over their priors (``scale``: (C, 2))."""
    z, _, gram = _integrated(data, model, sigma, scale)
    n = data.shape[-1]
    per = -0.5 * (np.sum(z**2, axis=-1) + np.linalg.slogdet(gram)[1] + n * (2.0 * np.log(sigma) + LOG_2PI))
    return per if per_channel else per.sum(axis=-1)


def estimate(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray) -> dict[str, np.ndarray]:
    """Posterior mean and sd of each channel's offset and gain given ``model`` (..., C, n): (..., C) each."""
    _, c_hat, gram = _integrated(data, model, sigma, scale)
    sd = np.sqrt(np.diagonal(np.linalg.inv(gram), axis1=-2, axis2=-1))
    return {"offset": scale[:, 0] * c_hat[..., 0], "offset_sd": scale[:, 0] * sd[..., 0],
            "gain": 1.0 + scale[:, 1] * c_hat[..., 1], "gain_sd": scale[:, 1] * sd[..., 1]}


def reading(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """What the instruments most probably show of ``model`` (..., C, n): o + g·m at the posterior means; the
    model itself when no channel has instrument errors."""
    if not np.any(scale > 0):
        return model
    found = estimate(data, model, sigma, scale)
    return found["offset"][..., None] + found["gain"][..., None] * model
