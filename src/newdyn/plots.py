"""Figures of a study: grid posteriors as in the paper's Figs. 3 and 4, summary heatmaps, MCMC
diagnostics, and the best-fitting models against the data.

Every figure function writes ``<name>.png`` and ``<name>.pdf`` (each atomically, with the code hash,
the versions and the input files in the metadata) and returns the Figure, so tests can inspect what
was drawn.  Figures are plain :class:`matplotlib.figure.Figure` objects: no pyplot, no global state.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np
import scipy.signal
import xarray as xr
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from . import io, model, provenance

PathLike = str | os.PathLike
PNG_DPI = 150
WELCH_SEGMENT = 1024  # samples per Welch segment: ~5 Hz resolution at 5 kHz, and a smooth average over 1 s
MARK_COLOR = "red"
CHI2_RED = r"$\chi^2_\mathrm{red}$"
ZOOM_SD = 6.0  # half-width of the zoomed posterior panel, in posterior standard deviations
HEATMAP_COLORS = matplotlib.colormaps["viridis"].with_extremes(bad="lightgrey")  # NaN cells grey


def save(fig: Figure, png_path: PathLike, code_hash: str = "", sources: Sequence[PathLike] = ()) -> None:
    """Write ``fig`` to ``png_path`` and to the PDF of the same stem, with provenance in the metadata."""
    png_path = Path(png_path)
    if png_path.suffix != ".png":
        raise ValueError(f"figure path must end in .png, got {png_path}")
    stamp = {**provenance.attributes(code_hash), "sources": json.dumps([os.fspath(s) for s in sources])}
    # PDF metadata takes only its standard keys: the stamp goes into Subject as JSON.  Without a
    # CreationDate a rerun writes the same bytes.
    pdf_metadata = {"Creator": f"newdyn {stamp['newdyn_version']}", "Subject": json.dumps(stamp), "CreationDate": None}
    io.atomic_write(png_path, lambda tmp: fig.savefig(tmp, format="png", dpi=PNG_DPI, metadata=stamp))
    io.atomic_write(png_path.with_suffix(".pdf"), lambda tmp: fig.savefig(tmp, format="pdf", metadata=pdf_metadata))


def posterior_panels(
    grid_result_paths: Sequence[PathLike], png_path: PathLike, title: str | None = None, code_hash: str = ""
) -> Figure:
    """Prior, likelihood and posterior of grid calibrations, one column per result side by side: the
    paper's Fig. 3 for one result, Fig. 4 for several.  The top row spans the grid as the paper does;
    the bottom row zooms in on the posterior, which at high SNR is a spike on the grid's scale."""
    results = [_load(path) for path in grid_result_paths]
    fig = Figure(figsize=(5.5 * len(results), 7.0), layout="constrained")
    axes = fig.subplots(2, len(results), squeeze=False, height_ratios=(3, 2))
    for i, result in enumerate(results):
        _posterior_panel(*axes[:, i], result, f"({chr(ord('a') + i)}) " if len(results) > 1 else "")
    if title:
        fig.suptitle(title)
    save(fig, png_path, code_hash, grid_result_paths)
    return fig


def _posterior_panel(full, zoom, result: xr.Dataset, label: str) -> None:
    attrs = result.attrs
    name = attrs["parameter"]
    grid = result["grid"].values
    for ax in (full, zoom):
        _draw_densities(ax, result)
    full.set_xlim(grid[0], grid[-1])
    # A posterior inside one grid cell (sd ~ 0) still gets a window of a thousandth of the grid.
    half_width = max(ZOOM_SD * float(attrs["sd"]), 1e-3 * (grid[-1] - grid[0]))
    mean = float(attrs["mean"])
    zoom.set_xlim(max(mean - half_width, grid[0]), min(mean + half_width, grid[-1]))
    full.set_title(f"{label}{name}: {_subject(attrs)}")
    zoom.set_title(f"zoom: posterior mean ± {ZOOM_SD:g} sd", fontsize="medium")
    full.legend(loc="upper right", fontsize="small")
    full.text(
        0.02, 0.97,
        f"{CHI2_RED} = {float(attrs['chi2_red']):.3g}\npeaks: {int(attrs['n_peaks'])}\n{attrs['verdict']}",
        transform=full.transAxes, va="top", color="black" if attrs["verdict"] == "explained" else MARK_COLOR,
        bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.8},
    )


def _draw_densities(ax, result: xr.Dataset) -> None:
    """Prior, scaled likelihood and posterior, with the original, true and MAP values as vertical lines."""
    attrs = result.attrs
    grid, posterior = result["grid"].values, result["posterior"].values
    ax.plot(grid, result["prior"].values, color="tab:blue", label="prior")
    ax.plot(grid, posterior, color="tab:green", label="posterior")
    # The likelihood is no density: as in the paper it is scaled to the posterior's peak to share the axis.
    # Drawn last and dashed, since under a flat prior it lies on the posterior.
    likelihood = result["scaled_likelihood"].values * posterior.max()
    ax.plot(grid, likelihood, color="tab:orange", ls="--", label="likelihood (scaled)")
    values = {
        "original value": (json.loads(attrs["settings"])["prior"]["mean"], "black", ":"),
        "true value": (float(attrs.get("true_value", math.nan)), "tab:red", "-."),
        "MAP": (float(attrs["map"]), "tab:green", "-"),
    }
    for text, (value, color, style) in values.items():
        if math.isfinite(value):  # the truth is unknown for a real measurement
            ax.axvline(value, color=color, ls=style, lw=1, label=f"{text} = {value:.4g}")
    unit = model.PARAMETER_BY_NAME[attrs["parameter"]].unit
    ax.set_xlabel(f"{attrs['parameter']} [{unit}]")
    ax.set_ylabel(f"probability density [1/({unit})]")
    ax.ticklabel_format(style="sci", scilimits=(-3, 4))


def heatmap(
    values,
    row_labels: Sequence[str],
    column_labels: Sequence[str],
    png_path: PathLike,
    title: str,
    colorbar_label: str,
    log: bool = False,
    code_hash: str = "",
    marks=None,
    *,
    limits: tuple[float, float] | None = None,
    mark_label: str = "marked",
    sources: Sequence[PathLike] = (),
) -> Figure:
    """A table of numbers as coloured cells with the value written in each (NaN cells grey and empty);
    cells where ``marks`` is True get a red frame, which the title explains with ``mark_label``."""
    fig = Figure(figsize=(2.5 + 1.1 * len(column_labels), 1.8 + 0.45 * len(row_labels)), layout="constrained")
    _draw_heatmap(fig, fig.subplots(), values, row_labels, column_labels, title, colorbar_label, log, marks, limits, mark_label)
    save(fig, png_path, code_hash, sources)
    return fig


def _draw_heatmap(fig, ax, values, row_labels, column_labels, title, colorbar_label, log=False, marks=None, limits=None,
                  mark_label="marked") -> None:
    values = np.asarray(values, dtype=float)
    marks = np.zeros(values.shape, bool) if marks is None else np.asarray(marks, dtype=bool)
    if values.shape != (len(row_labels), len(column_labels)) or marks.shape != values.shape:
        raise ValueError(
            f"values {values.shape} and marks {marks.shape} must both have shape (rows, columns) = "
            f"{(len(row_labels), len(column_labels))}"
        )
    norm = (LogNorm if log else Normalize)(*(limits or (None, None)))
    image = ax.imshow(np.ma.masked_invalid(values), cmap=HEATMAP_COLORS, norm=norm, aspect="auto")
    fig.colorbar(image, ax=ax, label=colorbar_label)
    ax.set_xticks(range(len(column_labels)), column_labels, rotation=45, ha="right", rotation_mode="anchor")
    ax.set_yticks(range(len(row_labels)), row_labels)
    for (row, column), value in np.ndenumerate(values):
        if np.isfinite(value):
            luminance = np.dot(image.to_rgba(value)[:3], (0.299, 0.587, 0.114))  # dark cells get white text
            color = "white" if luminance < 0.5 else "black"
            ax.text(column, row, f"{value:.3g}", ha="center", va="center", color=color)
    for row, column in np.argwhere(marks):
        ax.add_patch(Rectangle((column - 0.45, row - 0.45), 0.9, 0.9, fill=False, edgecolor=MARK_COLOR, lw=2.5))
    ax.set_title(title + (f"\nred frame: {mark_label}" if marks.any() else ""))


def signature_heatmaps(hellinger_path: PathLike, png_path: PathLike, snr_db: float, seed: int, code_hash: str = "") -> Figure:
    """The signature library of one SNR and seed (:func:`newdyn.comparison.signature_matrices`): one
    panel per calibration parameter, the Hellinger distance between every pair of scenarios' posteriors."""
    distances = _load(hellinger_path)["hellinger"].sel(snr_db=float(snr_db), seed=int(seed))
    parameters = [str(p) for p in distances["parameter"].values]
    scenarios = [str(s) for s in distances["scenario"].values]
    size = 2.0 + 0.55 * len(scenarios)
    fig = Figure(figsize=(size * len(parameters), size), layout="constrained")
    for ax, parameter in zip(fig.subplots(1, len(parameters), squeeze=False)[0], parameters):
        _draw_heatmap(fig, ax, distances.sel(parameter=parameter).values, scenarios, scenarios,
                      f"posteriors of {parameter}", "Hellinger distance", limits=(0.0, 1.0))
    fig.suptitle(f"Hellinger distance between scenarios' posteriors at {float(snr_db):g} dB, seed {int(seed)}")
    save(fig, png_path, code_hash, [hellinger_path])
    return fig


def summary_heatmaps(
    summary_csv: PathLike, hellinger_png: PathLike, chi2_png: PathLike, code_hash: str = ""
) -> tuple[Figure, Figure]:
    """Hellinger distance to the healthy posterior and reduced χ² of every grid calibration in the
    summary table: rows are scenarios, columns (variant:) parameter @ SNR; "not explained" cells are
    framed.  One table needs one seed: the lowest, named in the titles.
    """
    with open(summary_csv, newline="") as f:
        rows = [row for row in csv.DictReader(f) if row["method"] == "grid"]
    if not rows:
        raise ValueError(f"{summary_csv}: no grid calibrations")
    seed = min(int(row["seed"]) for row in rows)
    cells = {
        (row["scenario"], (row.get("variant", ""), row["parameter"], float(row["snr_db"]))): row
        for row in rows
        if int(row["seed"]) == seed
    }
    scenarios = sorted({s for s, _ in cells}, key=lambda s: (s != "healthy", s))  # the reference first
    # Variants side by side, the default first; within one, by parameter and falling SNR.
    columns = sorted({c for _, c in cells}, key=lambda c: (c[0] != "default", c[0], c[1], -c[2]))
    several = len({variant for variant, _, _ in columns}) > 1

    def table(column: str, convert=_number) -> np.ndarray:
        return np.array([[convert(cells.get((s, c), {}).get(column)) for c in columns] for s in scenarios])

    layout = {
        "row_labels": scenarios,
        "column_labels": [f"{f'{v}: ' if several else ''}{parameter} @ {snr:g} dB" for v, parameter, snr in columns],
        "code_hash": code_hash,
        "marks": table("verdict", lambda verdict: verdict == "not explained"),
        "mark_label": "not explained",
        "sources": [summary_csv],
    }
    subset = f"seed {seed}"
    hellinger = heatmap(
        table("hellinger_to_healthy"), png_path=hellinger_png, colorbar_label="Hellinger distance",
        title=f"Hellinger distance to the healthy posterior ({subset})", limits=(0.0, 1.0), **layout,
    )
    chi2 = heatmap(
        table("chi2_red"), png_path=chi2_png, colorbar_label="reduced χ²",
        title=f"Reduced χ² of the best fit ({subset})", log=True, **layout,
    )
    return hellinger, chi2


def mcmc_diagnostics(mcmc_paths: Sequence[PathLike], png_path: PathLike, code_hash: str = "") -> Figure:
    """Trace, marginal density and rank plots of every posterior variable of MCMC results (e.g. the 1-D
    and joint runs of one measurement), one block per run; each block's title gives R-hat and ESS
    and, in red, why the run did not converge."""
    import arviz as az  # slow to import: only this figure needs it

    from . import sampling

    runs = [sampling.load(path) for path in mcmc_paths]
    sizes = [len(idata.posterior.data_vars) for idata in runs]
    fig = Figure(figsize=(14, 1.2 * len(runs) + 2.6 * sum(sizes)), layout="constrained")
    for block, idata in zip(np.atleast_1d(fig.subfigures(len(runs), 1, height_ratios=sizes)), runs):
        attrs = idata.attrs  # netCDF attributes come back as text
        names = list(idata.posterior.data_vars)
        axes = block.subplots(len(names), 3, squeeze=False)
        az.plot_trace(idata, var_names=names, axes=axes[:, :2])
        az.plot_rank(idata, var_names=names, ax=axes[:, 2])
        converged = bool(int(float(attrs["converged"])))
        title = (
            f"MCMC {', '.join(names)}: {_subject(attrs)}\n"
            f"R-hat = {float(attrs['rhat']):.4f}, ESS bulk = {float(attrs['ess_bulk']):.0f}"
        )
        if not converged:
            title += f"\nUNCONVERGED: {attrs['reason']}"
        block.suptitle(title, color="black" if converged else MARK_COLOR, fontweight="normal" if converged else "bold")
    save(fig, png_path, code_hash, mcmc_paths)
    return fig


def model_overlays(
    measurement_path: PathLike,
    grid_result_paths: Sequence[PathLike],
    png_path: PathLike,
    window: float = 0.2,
    code_hash: str = "",
) -> Figure:
    """Where the best-fitting models fail: per channel, data and best fits over the first ``window``
    seconds (left), and the PSD of the data and of each fit's residual against the noise floor (right)."""
    measurement = io.read_measurement(measurement_path)
    results = [_load(path) for path in grid_result_paths]
    times, fs = measurement.sampling.times, measurement.sampling.fs
    for path, result in zip(grid_result_paths, results):
        missing = set(result["channel"].values) - set(measurement.channels)
        if missing:
            raise ValueError(f"{path}: channels {sorted(missing)} are not in {measurement_path}")
        if not np.allclose(result["time"].values, times, rtol=0.0, atol=io.TIME_JITTER / fs):
            raise ValueError(f"{path}: best fit is not sampled at the times of {measurement_path}")
    channels = list(dict.fromkeys(str(c) for result in results for c in result["channel"].values))

    fig = Figure(figsize=(14, 0.8 + 3.0 * len(channels)), layout="constrained")
    axes = fig.subplots(len(channels), 2, squeeze=False)
    shown = times < times[0] + window
    for (signal_ax, psd_ax), channel in zip(axes, channels):
        index = measurement.channels.index(channel)
        data = measurement.y[index]
        signal_ax.plot(times[shown], data[shown], color="black", lw=0.8, label="data")
        psd_ax.semilogy(*_psd(data, fs), color="black", lw=0.8, label="data")
        for result in results:
            if channel not in result["channel"]:
                continue
            fit = result["best_fit"].sel(channel=channel).values
            name = result.attrs["parameter"]
            label = f"{name} best fit ({CHI2_RED} = {float(result.attrs['chi2_red']):.3g})"
            (line,) = signal_ax.plot(times[shown], fit[shown], lw=0.8, label=label)
            psd_ax.semilogy(*_psd(data - fit, fs), color=line.get_color(), lw=0.8, label=f"data − {name} best fit")
        if measurement.sigma is not None:
            psd_ax.axhline(2 * measurement.sigma[index] ** 2 / fs, color="grey", ls="--", label="noise floor 2σ²/fs")
        unit = model.CHANNEL_UNITS[channel]
        signal_ax.set_ylabel(f"{channel} [{unit}]")
        psd_ax.set_ylabel(f"PSD [{unit}²/Hz]")
    for ax in axes[0]:
        ax.legend(loc="upper right", fontsize="small")
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("frequency [Hz]")
    fig.suptitle(f"Best-fitting models against {_subject({**measurement.attrs, 'measurement': measurement.name})}")
    save(fig, png_path, code_hash, [measurement_path, *grid_result_paths])
    return fig


def _psd(signal: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD without the zero-frequency bin, which the mean removal empties."""
    frequency, density = scipy.signal.welch(signal, fs=fs, nperseg=min(WELCH_SEGMENT, signal.size))
    return frequency[1:], density[1:]


def _subject(attrs) -> str:
    """What a result is about, e.g. "stick_slip, snr40_seed1" (a user's measurement has no scenario)."""
    return ", ".join(str(attrs[key]) for key in ("scenario", "measurement") if key in attrs)


def _load(path: PathLike) -> xr.Dataset:
    with xr.open_dataset(path, engine="netcdf4") as ds:
        return ds.load()


def _number(text: str | None) -> float:
    """A summary-table cell as a float; empty or absent cells are NaN."""
    return float(text) if text else math.nan
