"""Calibrate one rig parameter against one measurement on a likelihood grid (the paper's Section III).

The coarse grid of model runs depends only on the healthy rig, the operating condition and the
sampling, never on the data, so the workflow simulates it once per parameter (:func:`simulate_grid`)
and every measurement reuses it.  Each measurement then adds model runs around its own coarse
likelihood maxima (:func:`calibrate`): at 40 dB the likelihood is narrower than any affordable
uniform grid, and quadrature needs points across the peak.

The same parameters can be sampled by MCMC on the simulator (:mod:`newdyn.mcmc_calibration`); both
kinds of result end as rows of one summary table (:func:`summary_rows`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import xarray as xr

from . import concurrency, likelihood, model, sensors, simulation, slots

log = logging.getLogger("newdyn")

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
    def from_config(cls, name: str, grid: Mapping) -> GridSpec:
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
    channel_log_likelihood: np.ndarray | None = None  # each channel's share of the log-likelihood (grid point, channel)

    @property
    def n_peaks(self) -> int:
        return self.posterior.n_peaks()

    @property
    def verdict(self) -> str:
        """'explained' when the best fit brings χ² to the noise with a single likelihood peak."""
        return explanation_verdict(self.chi2_red, self.chi2_max, self.posterior.consistent(), converged=True)

    def summary(self) -> dict[str, float | int | str]:
        low, high = self.posterior.hdi()
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
    return simulate_points(values, [parameter], np.asarray(grid, dtype=float)[:, None], sampling, channels, max_step)


def simulate_points(
    values: Mapping[str, float],
    parameters: Sequence[str],
    points: np.ndarray,
    sampling: model.Sampling,
    channels: Sequence[str],
    max_step: float = simulation.DEFAULT_MAX_STEP,
) -> np.ndarray:
    """Model outputs (n, len(channels), n_samples) with ``parameters`` set to each row of ``points``
    (n, len(parameters)) and the others to ``values`` (missing names: the rig.md defaults)."""
    return simulation.simulate_batch(parameter_rows(values, parameters, points), sampling, channels, max_step)


def parameter_rows(values: Mapping[str, float], parameters: Sequence[str], points: np.ndarray) -> np.ndarray:
    """The kernel's parameter rows of :func:`simulate_points`."""
    params = np.tile(slots.parameter_vector(values), (len(points), 1))
    params[:, [model.PARAMETER_INDEX[p] for p in parameters]] = points
    return params


def grid_files(paths: Sequence[str]) -> dict[str, str]:
    """Coarse-grid files (``newdyn grid-models``) or a measurement's grid calibrations (``newdyn calibrate-grid``) by
    the parameter each holds, as its file says."""
    found = {}
    for path in paths:
        with xr.open_dataset(path, engine="netcdf4") as grid:
            found[str(grid.attrs["parameter"])] = path
    return found


def coarse_models(
    grid_path: str | None,
    spec: GridSpec,
    values: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    max_step: float = simulation.DEFAULT_MAX_STEP,
) -> np.ndarray:
    """The coarse-grid model runs of ``spec`` for the healthy rig ``values`` at ``sampling``: read from
    ``grid_path`` (the workflow's shared grid-model file) when it holds the same rig, operating
    condition, sampling, grid and channels, else simulated here."""
    if grid_path is not None:
        with xr.open_dataset(grid_path, engine="netcdf4") as coarse:
            coarse.load()
        same = (
            np.array_equal(coarse["time"].values, sampling.times)
            and np.array_equal(coarse["grid"].values, spec.axis)
            and set(channels) <= set(coarse["channel"].values.tolist())
            and slots.complete(json.loads(coarse.attrs["values"])) == slots.complete(values)
            and float(coarse.attrs["max_step"]) == max_step
        )
        if same:
            return coarse["model"].sel(channel=list(channels)).values
        log.info("%s: not this measurement's rig, sampling, grid or channels; simulating its grid", grid_path)
    return simulate_grid(values, spec.parameter, spec.axis, sampling, channels, max_step)


@dataclass(frozen=True)
class Task:
    """One grid calibration among several run together (:func:`calibrate_many`): ``data`` (channel, time) on the grid
    ``spec`` under ``prior``, its coarse model runs ``coarse_models`` (:func:`simulate_grid` on ``spec.axis``)."""

    data: np.ndarray
    spec: GridSpec
    prior: NormalPrior
    coarse_models: np.ndarray


# A refinement pass simulates the points of every task's cells at once, in batches of at most this many simulations
# (their outputs are scored and dropped batch by batch, so memory stays bounded however many tasks run together).
REFINE_BATCH = 512


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
    instruments: sensors.Instruments | None = None,
) -> Calibration:
    """Grid posterior of ``spec.parameter`` given ``data`` (channel, time) with known noise ``sigma`` (and the
    instruments' offsets, gains and delays integrated out, with ``instruments``: :mod:`newdyn.sensors`)

    ``coarse_models`` are :func:`simulate_grid`'s outputs on ``spec.axis`` for the model ``values``
    (the healthy rig at the measurement's operating condition and sampling).
    """
    return calibrate_many([Task(data, spec, prior, coarse_models)], sigma, values, sampling, channels, refine_points, chi2_max,
                          max_step, instruments)[0]


class _Run(NamedTuple):
    """One set of a calibration's points (its coarse grid, or a peak's cell or span): each channel's log-likelihood
    there and their sum, and the row and model of its best point, the only model kept (the passes' outputs are tens
    of MB)."""

    grid: np.ndarray
    per_channel: np.ndarray
    log_likelihood: np.ndarray
    best: int
    best_model: np.ndarray


def calibrate_many(tasks: Sequence[Task], sigma: np.ndarray, values: Mapping[str, float], sampling: model.Sampling,
                   channels: Sequence[str], refine_points: int, chi2_max: float, max_step: float = simulation.DEFAULT_MAX_STEP,
                   instruments: sensors.Instruments | None = None) -> list[Calibration]:
    """:func:`calibrate` of each of ``tasks`` (all with noise ``sigma`` through ``instruments``), each refinement pass
    of them all simulated together: the kernel fills its lanes and both cores, where one task's cells of
    ``refine_points`` would not, and a cell that several tasks refine is simulated once.  Each task's result is the one
    it gets alone, to the bit.  The likelihoods of its runs are evaluated side by side in threads."""
    def run(task, grid, models):
        per_channel = likelihood.log_likelihood(task.data, models, sigma, per_channel=True, instruments=instruments)
        ll = per_channel.sum(axis=-1)
        best = int(np.argmax(ll))
        return _Run(grid, per_channel, ll, best, models[best].copy())

    def refined(cells):  # [(task number, points)] -> each cell's run
        # Cells of one parameter at the same points (tasks whose peaks fall in one coarse cell: a library's signatures,
        # mostly) are simulated once for all of them; a lane's result does not depend on its batch.
        same = {}
        for c, (k, points) in enumerate(cells):
            same.setdefault((tasks[k].spec.parameter, points.tobytes()), []).append(c)
        groups, found, per_batch = list(same.values()), {}, max(1, REFINE_BATCH // refine_points)
        for start in range(0, len(groups), per_batch):
            batch = [(cells[group[0]], group) for group in groups[start:start + per_batch]]
            models = simulation.simulate_parts([parameter_rows(values, [tasks[k].spec.parameter], points[:, None]) for (k, points), _ in batch],
                                               sampling, channels, max_step)
            found.update(concurrency.in_parallel({
                c: lambda c=c, points=points, cell_models=cell_models: run(tasks[cells[c][0]], points, cell_models)
                for ((_, points), group), cell_models in zip(batch, models) for c in group}))
        return [found[c] for c in range(len(cells))]

    coarse_runs = list(concurrency.in_parallel({k: lambda task=task: run(task, task.spec.axis, task.coarse_models)
                                                for k, task in enumerate(tasks)}).values())
    # Pass 1 finds each peak inside its coarse cells; pass 2 covers ±SPAN_SD widths of it, so that quadrature sees the
    # whole peak and not a linear interpolation across a coarse cell.
    cells = []
    for k, task in enumerate(tasks):
        coarse = task.spec.axis
        cells += [(k, np.linspace(coarse[max(i - 1, 0)], coarse[min(i + 1, coarse.size - 1)], refine_points))
                  for i in _highest_maxima(coarse_runs[k].log_likelihood)]
    cell_runs = refined(cells)
    spans = []
    for (k, _), cell in zip(cells, cell_runs):
        center, width = _peak_and_width(cell.grid, cell.log_likelihood)
        spec = tasks[k].spec
        spans.append((k, np.linspace(max(center - SPAN_SD * width, spec.low), min(center + SPAN_SD * width, spec.high), refine_points)))
    runs = [[coarse_run] for coarse_run in coarse_runs]  # each task's coarse grid, then each peak's cell and span
    for (k, _), cell_run, span_run in zip(cells, cell_runs, refined(spans)):
        runs[k] += [cell_run, span_run]
    return [_calibration(task, task_runs, sigma, chi2_max, instruments) for task, task_runs in zip(tasks, runs)]


def _calibration(task: Task, runs: Sequence[_Run], sigma, chi2_max, instruments) -> Calibration:
    """A task's posterior on all its runs' points, and the reduced χ² of its best model."""
    grid, unique = np.unique(np.concatenate([r.grid for r in runs]), return_index=True)
    ll = np.concatenate([r.log_likelihood for r in runs])[unique]
    posterior = likelihood.grid_posterior(grid, ll, task.prior.log_pdf(grid))
    # The best of all points is its run's best: every run's grid ascends, and np.argmax over the sorted points and over
    # the run both take the lowest of tied maxima.
    part, row = _part_and_row([len(r.grid) for r in runs], int(unique[np.argmax(ll)]))
    assert runs[part].best == row
    chi2 = float(likelihood.reduced_chi2(task.data, runs[part].best_model, sigma, n_fitted=1, instruments=instruments))
    return Calibration(posterior, task.prior.sd, chi2, runs[part].best_model, chi2_max,
                       np.concatenate([r.per_channel for r in runs])[unique])


def _part_and_row(sizes: Sequence[int], index: int) -> tuple[int, int]:
    """Which of consecutive parts of ``sizes`` rows holds row ``index`` of them all, and its row there."""
    part = int(np.searchsorted(np.cumsum(sizes), index, side="right"))
    return part, index - int(np.sum(sizes[:part]))


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


def explanation_verdict(chi2_red: float, chi2_max: float, consistent: bool, converged: bool) -> str:
    """'explained' when the best fit brings χ² to the noise with one peak inside the grid
    (:meth:`likelihood.GridPosterior.consistent`); an unconverged MCMC run gets no verdict."""
    if not converged:
        return "unconverged"
    return "explained" if chi2_red <= chi2_max and consistent else "not explained"


SUMMARY_COLUMNS = (
    "variant", "scenario", "parameter", "snr_db", "seed", "method", "map", "mean", "sd", "hdi_low", "hdi_high",
    "sd_ratio", "n_peaks", "chi2_red", "rhat", "ess_bulk", "converged", "verdict", "hellinger_to_healthy",
    "hellinger_to_grid", "jointly",
)


def summary_rows(results: Sequence[Mapping]) -> list[dict]:
    """One summary row per calibration result, with the Hellinger distance of its posterior to the
    healthy scenario's for the same variant, parameter, SNR, seed and method (the paper's Step 3).

    Each result is a mapping of its summary attributes plus ``grid`` and ``posterior`` arrays.
    """
    from .comparison import hellinger_densities

    def key(r):
        return r.get("variant", ""), r["parameter"], r["snr_db"], r["seed"], r["method"], r.get("jointly", "")

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
        if isinstance(row["converged"], (bool, np.bool_)):  # as netCDF stores it: 1 or 0
            row["converged"] = int(row["converged"])
        row["hellinger_to_healthy"] = distance
        rows.append(row)
    return sorted(rows, key=lambda row: (row["variant"], row["scenario"], row["jointly"], row["parameter"], row["snr_db"], row["seed"], row["method"]))
