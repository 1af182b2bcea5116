"""Calibrate one rig parameter against one measurement on a likelihood grid (the paper's Section III).

The coarse grid of model runs depends only on the healthy rig, the operating condition and the
sampling, never on the data, so the workflow simulates it once per parameter (:func:`simulate_grid`)
and every measurement reuses it.  Each measurement then adds model runs around its own coarse
likelihood maxima (:func:`calibrate`): at 40 dB the likelihood is narrower than any affordable
uniform grid, and quadrature needs points across the peak.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from . import likelihood, model, simulation

N_REFINED_MAXIMA = 3  # coarse likelihood maxima refined per measurement: enough to see multiple peaks


@dataclass(frozen=True)
class GridSpec:
    """The coarse likelihood grid of a calibration parameter (config ``calibration.parameters.<name>.grid``)."""

    parameter: str
    low: float
    high: float
    points: int

    @classmethod
    def from_config(cls, name: str, grid: Mapping) -> "GridSpec":
        return cls(name, float(grid["low"]), float(grid["high"]), int(grid["points"]))

    @property
    def axis(self) -> np.ndarray:
        return np.linspace(self.low, self.high, self.points)


@dataclass(frozen=True)
class NormalPrior:
    mean: float
    sd: float

    def log_pdf(self, x: np.ndarray) -> np.ndarray:
        return likelihood.gaussian_log_prior(x, self.mean, self.sd)


@dataclass(frozen=True)
class Calibration:
    """The grid posterior of one parameter for one measurement, and how well its best fit explains the data."""

    posterior: likelihood.GridPosterior
    prior_sd: float
    chi2_red: float  # reduced χ² of the best-fitting (maximum-likelihood) grid model
    best_fit: np.ndarray  # that model's outputs (channel, time)
    chi2_max: float

    @property
    def n_peaks(self) -> int:
        return self.posterior.n_peaks()

    @property
    def verdict(self) -> str:
        """'explained' when the best fit brings χ² to the noise with a single likelihood peak."""
        return "explained" if self.chi2_red <= self.chi2_max and self.n_peaks == 1 else "not explained"

    def summary(self) -> dict[str, float | int | str]:
        low, high = self.posterior.hdi(0.94)
        return {
            "map": self.posterior.map,
            "mean": self.posterior.mean,
            "sd": self.posterior.sd,
            "hdi_low": low,
            "hdi_high": high,
            "sd_ratio": self.posterior.sd / self.prior_sd,
            "n_peaks": self.n_peaks,
            "chi2_red": self.chi2_red,
            "verdict": self.verdict,
        }


def simulate_grid(
    values: Mapping[str, float],
    parameter: str,
    grid: np.ndarray,
    sampling: model.Sampling,
    channels: Sequence[str],
    max_step: float = simulation.DEFAULT_MAX_STEP,
) -> np.ndarray:
    """Model outputs (len(grid), len(channels), n_samples) with ``parameter`` set to each grid value."""
    params = np.tile(model.parameter_vector(values), (len(grid), 1))
    params[:, model.PARAMETER_INDEX[parameter]] = grid
    return simulation.simulate_batch(params, sampling, channels, max_step)


def calibrate(
    data: np.ndarray,
    sigma: np.ndarray,
    spec: GridSpec,
    prior: NormalPrior,
    coarse_models: np.ndarray,
    values: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    refine_points: int,
    chi2_max: float,
    max_step: float = simulation.DEFAULT_MAX_STEP,
) -> Calibration:
    """Grid posterior of ``spec.parameter`` given ``data`` (channel, time) with known noise ``sigma``.

    ``coarse_models`` are :func:`simulate_grid`'s outputs on ``spec.axis`` for the model ``values``
    (the healthy rig at the measurement's operating condition and sampling).
    """
    coarse = spec.axis
    coarse_ll = likelihood.log_likelihood(data, coarse_models, sigma)
    fine = _refinement(coarse, coarse_ll, refine_points)
    fine_models = simulate_grid(values, spec.parameter, fine, sampling, channels, max_step)
    grid, unique = np.unique(np.concatenate([coarse, fine]), return_index=True)
    models = np.concatenate([coarse_models, fine_models])[unique]
    ll = likelihood.log_likelihood(data, models, sigma)
    posterior = likelihood.grid_posterior(grid, ll, prior.log_pdf(grid))
    best = models[np.argmax(ll)]
    chi2 = float(likelihood.reduced_chi2(data, best, sigma, n_fitted=1))
    return Calibration(posterior, prior.sd, chi2, best, chi2_max)


def _refinement(grid: np.ndarray, log_like: np.ndarray, points: int) -> np.ndarray:
    """Points across the cells next to the highest local maxima of the coarse log-likelihood."""
    padded = np.concatenate(([-np.inf], log_like, [-np.inf]))
    maxima = np.flatnonzero((padded[1:-1] >= padded[:-2]) & (padded[1:-1] >= padded[2:]))
    best = maxima[np.argsort(log_like[maxima])[::-1][:N_REFINED_MAXIMA]]
    last = grid.size - 1
    return np.concatenate([np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, last)], points) for i in best])


SUMMARY_COLUMNS = (
    "scenario", "parameter", "snr_db", "seed", "method", "map", "mean", "sd", "hdi_low", "hdi_high",
    "sd_ratio", "n_peaks", "chi2_red", "rhat", "ess_bulk", "converged", "verdict", "hellinger_to_healthy",
)


def summary_rows(results: Sequence[Mapping]) -> list[dict]:
    """One summary row per calibration result, with the Hellinger distance of its posterior to the
    healthy scenario's for the same parameter, SNR, seed and method (the paper's Step 3).

    Each result is a mapping of its summary attributes plus ``grid`` and ``posterior`` arrays.
    """
    from .comparison import hellinger_densities

    def key(r):
        return r["parameter"], r["snr_db"], r["seed"], r["method"]

    healthy = {key(r): r for r in results if r["scenario"] == "healthy"}
    rows = []
    for r in results:
        reference = healthy.get(key(r))
        distance = (
            hellinger_densities(r["grid"], r["posterior"], reference["grid"], reference["posterior"])
            if reference is not None
            else float("nan")
        )
        row = {column: r.get(column, "") for column in SUMMARY_COLUMNS}
        row["hellinger_to_healthy"] = distance
        rows.append(row)
    return sorted(rows, key=lambda row: (row["scenario"], row["parameter"], row["snr_db"], row["seed"], row["method"]))
