"""Calibrate one rig parameter against one measurement on a likelihood grid (the paper's Section III).

The coarse grid of model runs depends only on the healthy rig, the operating condition and the
sampling, never on the data, so the workflow simulates it once per parameter (:func:`simulate_grid`)
and every measurement reuses it.  Each measurement then adds model runs around its own coarse
likelihood maxima (:func:`calibrate`): at 40 dB the likelihood is narrower than any affordable
uniform grid, and quadrature needs points across the peak.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
import xarray as xr

from . import likelihood, model, simulation

if TYPE_CHECKING:  # sampling imports arviz (slow); only the MCMC path needs it at run time
    from .sampling import MCMCSettings

N_REFINED_MAXIMA = 3  # coarse likelihood maxima refined per measurement: enough to see multiple peaks
SPAN_SD = 6.0  # refined span around each peak, in likelihood widths


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
    def run(points):
        models = simulate_grid(values, spec.parameter, points, sampling, channels, max_step)
        return models, likelihood.log_likelihood(data, models, sigma)

    coarse = spec.axis
    coarse_ll = likelihood.log_likelihood(data, coarse_models, sigma)
    grids, all_models, all_ll = [coarse], [coarse_models], [coarse_ll]
    for i in _highest_maxima(coarse_ll):
        # Pass 1 finds the peak inside its coarse cells; pass 2 covers ±SPAN_SD widths of it, so that
        # quadrature sees the whole peak and not a linear interpolation across a coarse cell.
        cell = np.linspace(coarse[max(i - 1, 0)], coarse[min(i + 1, coarse.size - 1)], refine_points)
        cell_models, cell_ll = run(cell)
        center, width = _peak_and_width(cell, cell_ll)
        span = np.linspace(max(center - SPAN_SD * width, spec.low), min(center + SPAN_SD * width, spec.high), refine_points)
        span_models, span_ll = run(span)
        grids += [cell, span]
        all_models += [cell_models, span_models]
        all_ll += [cell_ll, span_ll]
    grid, unique = np.unique(np.concatenate(grids), return_index=True)
    models = np.concatenate(all_models)[unique]
    ll = np.concatenate(all_ll)[unique]
    posterior = likelihood.grid_posterior(grid, ll, prior.log_pdf(grid))
    best = models[np.argmax(ll)]
    chi2 = float(likelihood.reduced_chi2(data, best, sigma, n_fitted=1))
    return Calibration(posterior, prior.sd, chi2, best, chi2_max)


def _highest_maxima(log_like: np.ndarray) -> np.ndarray:
    """Indices of the highest local maxima (grid ends included) of a coarse log-likelihood."""
    padded = np.concatenate(([-np.inf], log_like, [-np.inf]))
    maxima = np.flatnonzero((padded[1:-1] >= padded[:-2]) & (padded[1:-1] >= padded[2:]))
    return maxima[np.argsort(log_like[maxima])[::-1][:N_REFINED_MAXIMA]]


def _peak_and_width(grid: np.ndarray, log_like: np.ndarray) -> tuple[float, float]:
    """Location of the log-likelihood maximum and the width of the peak there.

    Inside the grid the Gaussian width 1/sqrt(-d²ℓ/dφ²); at a grid end, where the likelihood is still
    rising (the peak lies beyond the bound), the decay length 1/|dℓ/dφ| of the exponential tail that
    the bound cuts.  Where neither is defined, the grid's span.
    """
    k, last = int(np.argmax(log_like)), grid.size - 1
    step = grid[1] - grid[0]
    if 0 < k < last:
        curvature = (log_like[k - 1] - 2 * log_like[k] + log_like[k + 1]) / step**2
        if curvature < 0:
            return float(grid[k]), float(1 / np.sqrt(-curvature))
    else:
        slope = abs(log_like[k] - log_like[k - 1 if k else 1]) / step
        if slope > 0:
            return float(grid[k]), float(1 / slope)
    return float(grid[k]), float(grid[-1] - grid[0])


def calibrate_mcmc(
    data: np.ndarray,
    sigma: np.ndarray,
    spec: GridSpec,
    prior: NormalPrior,
    grid_posterior: likelihood.GridPosterior,
    values: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    settings: MCMCSettings,
    max_step: float = simulation.DEFAULT_MAX_STEP,
    attrs: Mapping[str, object] | None = None,
):
    """MCMC posterior (emcee, ArviZ InferenceData) of ``spec.parameter`` on the real simulator.

    The prior is the Normal prior truncated to the grid range, so MCMC and the grid target the same
    posterior and their Hellinger distance is a check of both.  Walkers start from draws of the grid
    posterior: the chains start stationary and need little burn-in.
    """
    from . import sampling as mcmc

    index = model.PARAMETER_INDEX[spec.parameter]
    base = model.parameter_vector(values)

    def log_likelihood(theta):
        params = np.tile(base, (len(theta), 1))
        params[:, index] = theta[:, 0]
        return likelihood.log_likelihood(data, simulation.simulate_batch(params, sampling, channels, max_step), sigma)

    def log_prior(theta):
        x = theta[:, 0]
        return np.where((x >= spec.low) & (x <= spec.high), prior.log_pdf(x), -np.inf)

    rng = np.random.default_rng(settings.seed)
    initial = np.interp(rng.uniform(size=settings.n_walkers), grid_posterior.cdf, grid_posterior.grid)[:, None]
    prior_draws = rng.normal(prior.mean, prior.sd, 4 * settings.n_steps)
    prior_draws = prior_draws[(prior_draws >= spec.low) & (prior_draws <= spec.high)]
    return mcmc.run(
        log_likelihood, log_prior, [spec.parameter], initial, settings,
        prior_samples={spec.parameter: prior_draws},
        observed={"y": xr.DataArray(data, dims=("channel", "time"), coords={"channel": list(channels), "time": sampling.times})},
        attrs=attrs,
    )


def mcmc_summary(
    idata, parameter: str, prior: NormalPrior, grid_posterior: likelihood.GridPosterior, sigma: np.ndarray, chi2_max: float
) -> dict:
    """The summary row of an MCMC calibration, with its agreement with the grid posterior."""
    import arviz as az

    from .comparison import hellinger_samples_to_density

    draws = idata.posterior[parameter].values.ravel()
    best = np.unravel_index(np.argmax(idata.sample_stats["lp"].values), idata.sample_stats["lp"].shape)
    n_samples = idata.observed_data["y"].shape[-1]
    best_ll = float(idata.sample_stats["log_likelihood"].values.max())
    chi2_red = likelihood.chi2_from_log_likelihood(best_ll, sigma, n_samples) / (sigma.size * n_samples - 1)
    low, high = az.hdi(draws, hdi_prob=0.94)
    converged = bool(idata.attrs["converged"])
    n_peaks = grid_posterior.n_peaks()
    explained = chi2_red <= chi2_max and n_peaks == 1
    return {
        "map": float(idata.posterior[parameter].values[best]),
        "mean": float(draws.mean()),
        "sd": float(draws.std(ddof=1)),
        "hdi_low": float(low),
        "hdi_high": float(high),
        "sd_ratio": float(draws.std(ddof=1) / prior.sd),
        "n_peaks": n_peaks,
        "chi2_red": chi2_red,
        "rhat": float(idata.attrs["rhat"]),
        "ess_bulk": float(idata.attrs["ess_bulk"]),
        "converged": converged,
        "verdict": ("explained" if explained else "not explained") if converged else "unconverged",
        "hellinger_to_grid": hellinger_samples_to_density(
            draws, grid_posterior.grid, grid_posterior.density, bounds=(grid_posterior.grid[0], grid_posterior.grid[-1])
        ),
    }


SUMMARY_COLUMNS = (
    "scenario", "parameter", "snr_db", "seed", "method", "map", "mean", "sd", "hdi_low", "hdi_high",
    "sd_ratio", "n_peaks", "chi2_red", "rhat", "ess_bulk", "converged", "verdict", "hellinger_to_healthy",
    "hellinger_to_grid",
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
