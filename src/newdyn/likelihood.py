"""Gaussian likelihood of data given model outputs, and posteriors on a parameter grid by quadrature.

The calibration of Section III of the paper, p(φ|y) ∝ p(φ) p(y|φ), for one parameter φ simulated on a
1-D grid: :func:`log_likelihood` scores each grid point's model outputs against the data under
independent Gaussian noise of known per-channel σ, and :func:`grid_posterior` turns the scores and a
log prior into a :class:`GridPosterior` — a density normalized by trapezoidal quadrature, its summaries,
and the likelihood scaled to a maximum of 1 so it can be drawn on the same axis as the densities, as
in the paper's figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal, stats
from scipy.integrate import cumulative_trapezoid, trapezoid

from . import sensors

HDI_PROB = 0.94  # the credible intervals newdyn reports: ArviZ's default, 94 % highest density


def _checked(data, model, sigma) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``data``, ``model`` and ``sigma`` as float arrays, their shapes checked; ``model`` and ``sigma`` may carry
    leading axes that broadcast (e.g. one model and one σ per MCMC walker)."""
    data, model, sigma = (np.asarray(a, dtype=float) for a in (data, model, sigma))
    if data.ndim != 2:
        raise ValueError(f"data must be (n_channels, n_samples), got shape {data.shape}")
    if model.shape[-2:] != data.shape:
        raise ValueError(f"model must be (..., {data.shape[0]}, {data.shape[1]}), got shape {model.shape}")
    if sigma.ndim < 1 or sigma.shape[-1] != data.shape[0] or not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(f"sigma must be (..., {data.shape[0]}) positive finite values, got {sigma!r}")
    return data, model, sigma


def standardized_residuals(data, model, sigma, instruments: sensors.Instruments | None = None) -> np.ndarray:
    """(..., C, n) misfits (y − m)/σ, or with ``instruments`` (:mod:`newdyn.sensors`) (..., C, n + k) numbers
    whose squares sum to the same quadratic form as the marginal likelihood's."""
    data, model, sigma = _checked(data, model, sigma)
    if instruments is None:
        return (data - model) / sigma[..., None]
    return sensors.standardized_residuals(data, model, sigma, instruments)


# Models scored at a time: a batch's misfit of many rows at once would be a temporary of hundreds of megabytes, whose
# allocation and memory traffic cost more than the simulations behind it; a few rows' stays in the cache.
SCORED_ROWS = 64


def _sum_of_squares(data: np.ndarray, model: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Σ_k ((y_ck − m_ck)/σ_c)² per leading index and channel, rows of a batch of models (n, C, T) under one σ (C,)
    a few at a time; each row's sum is the same numbers in the same order as for the whole batch at once."""
    if model.ndim != 3 or sigma.ndim != 1:
        return np.sum(((data - model) / sigma[..., None]) ** 2, axis=-1)
    squares = np.empty(model.shape[:2])
    for start in range(0, len(model), SCORED_ROWS):
        rows = slice(start, start + SCORED_ROWS)
        squares[rows] = np.sum(((data - model[rows]) / sigma[:, None]) ** 2, axis=-1)
    return squares


def log_likelihood(data, model, sigma, per_channel: bool = False, instruments: sensors.Instruments | None = None) -> np.ndarray:
    """Normalized Gaussian log-likelihood log p(y | m) of ``data`` given ``model`` outputs.

    Σ_c Σ_k [−½((y_ck − m_ck)/σ_c)² − log σ_c − ½ log 2π], noise independent over channels and samples;
    with ``instruments``, each channel's instrument offset, gain and delay integrated over their priors
    (:mod:`newdyn.sensors`).

    Parameters
    ----------
    data : (n_channels, n_samples) measured outputs y.
    model : (..., n_channels, n_samples) model outputs m, e.g. one per grid point.
    sigma : (n_channels,) noise standard deviation per channel, or (..., n_channels) one σ per model
        (leading axes broadcast against the model's, e.g. one model and one σ per MCMC walker).
    per_channel : return the terms of each channel instead of their sum.

    Returns
    -------
    (...) or, with ``per_channel``, (..., n_channels); ``...`` is the broadcast of the leading axes.
    """
    data, model, sigma = _checked(data, model, sigma)
    if instruments is not None:
        return sensors.log_likelihood(data, model, sigma, instruments, per_channel)
    # The normalization matters only when σ or the channel set differs between compared likelihoods,
    # but keeping it makes the value a true log density of the data.
    normalization = data.shape[-1] * (np.log(sigma) + 0.5 * np.log(2 * np.pi))
    per = -0.5 * _sum_of_squares(data, model, sigma) - normalization
    return per if per_channel else per.sum(axis=-1)


def reduced_chi2(data, model, sigma, n_fitted: int = 0, instruments: sensors.Instruments | None = None) -> np.ndarray:
    """Σ((y − m)/σ)² / (N − n_fitted) over all N observations; ≈ 1 when the model explains the data (with
    ``instruments``, the misfit left after the instruments' offsets, gains and delays, their prior terms included, and
    whitened when their noise is coloured).

    ``model`` may carry leading grid axes like in :func:`log_likelihood`; the result has those axes.
    """
    n_samples = np.shape(data)[-1] - (instruments.presamples if instruments is not None else 0)
    dof = np.shape(data)[-2] * n_samples - n_fitted
    z = standardized_residuals(data, model, sigma, instruments)
    if dof <= 0:
        raise ValueError(f"{n_fitted} fitted parameters leave no degrees of freedom for {dof + n_fitted} observations")
    return np.sum(z**2, axis=(-2, -1)) / dof


def chi2_from_log_likelihood(log_like: float, sigma: np.ndarray, n_samples: int) -> float:
    """Σ((y − m)/σ)² recovered from a :func:`log_likelihood` value over n_samples per channel."""
    sigma = np.asarray(sigma, dtype=float)
    constant = -n_samples * (np.sum(np.log(sigma)) + 0.5 * sigma.size * np.log(2 * np.pi))
    return float(-2.0 * (log_like - constant))


def gaussian_log_prior(grid, mean: float, sd: float) -> np.ndarray:
    """log N(grid; mean, sd²), e.g. the paper's prior N(3e6, 0.5e6²) N/m on kT1."""
    return stats.norm.logpdf(np.asarray(grid, dtype=float), loc=mean, scale=sd)


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)  # eq on arrays is ambiguous; compare fields explicitly
class GridPosterior:
    """A 1-D posterior on a grid of parameter values; build it with :func:`grid_posterior`.

    Attributes
    ----------
    grid : increasing parameter values φ_i.
    log_likelihood, log_prior : the inputs, per grid point.
    density : posterior pdf, integrating to 1 over the grid by the trapezoidal rule.
    scaled_likelihood : likelihood divided by its maximum (not a density; for plotting and peak counting).
    prior_density : exp(log_prior) as given, not renormalized to the grid, so a prior truncated by the
        grid shows how much of it the grid covers.
    """

    grid: np.ndarray
    log_likelihood: np.ndarray
    log_prior: np.ndarray
    density: np.ndarray
    scaled_likelihood: np.ndarray
    prior_density: np.ndarray

    @property
    def map(self) -> float:
        """Grid point of highest posterior density (the first, on a plateau)."""
        return float(self.grid[np.argmax(self.density)])

    @property
    def mean(self) -> float:
        return float(trapezoid(self.grid * self.density, self.grid))

    @property
    def sd(self) -> float:
        return float(np.sqrt(trapezoid((self.grid - self.mean) ** 2 * self.density, self.grid)))

    @property
    def cdf(self) -> np.ndarray:
        """Posterior probability of φ ≤ grid_i, by cumulative trapezoid (0 at the first point, 1 at the last)."""
        return cumulative_trapezoid(self.density, self.grid, initial=0.0)

    def hdi(self, prob: float = HDI_PROB) -> tuple[float, float]:
        """(low, high) grid points bounding the highest-density region holding at least ``prob``.

        Grid points are taken in order of decreasing density, each carrying the mass of its trapezoid
        cell, until ``prob`` is reached.  For a multimodal posterior the selected points may form
        several separate intervals; this returns the span from the lowest to the highest, which then
        covers the low-density gaps between modes too — check :meth:`n_peaks` before reading it as one
        credible interval.
        """
        if not 0 < prob <= 1:
            raise ValueError(f"prob must be in (0, 1], got {prob}")
        cell_widths = _trapezoid_weights(self.grid)
        order = np.argsort(self.density, kind="stable")[::-1]
        mass = np.cumsum(self.density[order] * cell_widths[order])
        # Compare with the total rather than 1 so rounding cannot leave prob=1 unreached.
        n_selected = min(int(np.searchsorted(mass, prob * mass[-1])), mass.size - 1) + 1
        selected = self.grid[order[:n_selected]]
        return float(selected.min()), float(selected.max())

    def consistent(self) -> bool:
        """One likelihood peak, inside the grid: what a calibration that explains the data gives.

        A likelihood highest at a grid end says the best fit lies beyond the grid (±3 prior sd by
        default): not a plausible drift of the parameter but a sign that it absorbs something else.
        """
        highest = int(np.argmax(self.scaled_likelihood))
        return self.n_peaks() == 1 and 0 < highest < self.grid.size - 1

    def n_peaks(self, min_prominence: float = 0.05) -> int:
        """Number of peaks of the scaled likelihood with prominence ≥ ``min_prominence`` (of its max).

        The paper reads several distinct likelihood peaks as the sign that calibrating this parameter
        cannot explain the data.  The likelihood is taken as zero just outside the grid, so a likelihood
        still rising at a grid bound counts as a peak there: the grid cut the mode, it did not remove it.
        """
        padded = np.concatenate(([0.0], self.scaled_likelihood, [0.0]))
        peaks, _ = signal.find_peaks(padded, prominence=min_prominence)
        return int(peaks.size)


def _trapezoid_weights(grid: np.ndarray) -> np.ndarray:
    """Width of each grid point's cell, so that Σ f_i w_i is the trapezoidal rule ∫ f."""
    half_spacing = np.diff(grid) / 2
    weights = np.zeros(grid.size)
    weights[:-1] += half_spacing
    weights[1:] += half_spacing
    return weights


def grid_posterior(grid, log_likelihood_values, log_prior_values) -> GridPosterior:
    """Posterior on ``grid`` from per-point log-likelihoods and log prior (a scalar, e.g. 0, is a flat prior).

    Normalization subtracts the maximum log posterior before exponentiating, so log-likelihoods of
    −1e6 whose differences are thousands still give a finite density (possibly nonzero at one point
    only).  −inf entries mean zero probability; NaN entries are refused as they signal a failed
    simulation, not an impossible parameter value.
    """
    grid = np.asarray(grid, dtype=float)
    if grid.ndim != 1 or grid.size < 2 or not np.all(np.isfinite(grid)) or np.any(np.diff(grid) <= 0):
        raise ValueError("grid must be a 1-D, finite, strictly increasing array of at least 2 points")
    log_like = np.broadcast_to(np.asarray(log_likelihood_values, dtype=float), grid.shape)
    log_prior = np.broadcast_to(np.asarray(log_prior_values, dtype=float), grid.shape)
    log_post = log_like + log_prior
    if np.any(np.isnan(log_post)) or np.any(log_post == np.inf):
        raise ValueError("log-likelihood and log prior must not be NaN or +inf")
    if not np.any(np.isfinite(log_post)):
        raise ValueError("posterior is zero at every grid point (all log-likelihood + log prior are -inf)")

    unnormalized = np.exp(log_post - log_post.max())
    return GridPosterior(
        grid=_read_only(grid),
        log_likelihood=_read_only(log_like),
        log_prior=_read_only(log_prior),
        density=_read_only(unnormalized / trapezoid(unnormalized, grid)),
        scaled_likelihood=_read_only(np.exp(log_like - log_like.max())),
        prior_density=_read_only(np.exp(log_prior)),
    )
