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
from collections.abc import Sequence
from pathlib import Path

import matplotlib
import numpy as np
import scipy  # subpackages load on first use: most figures never need scipy.signal
import xarray as xr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import NullLocator

from . import io, model, noise, provenance, residuals

PathLike = str | os.PathLike
PNG_DPI = 150
WELCH_SEGMENT = 1024  # samples per Welch segment: ~5 Hz resolution at 5 kHz, and a smooth average over 1 s
MARK_COLOR = "red"
CHI2_RED = r"$\chi^2_\mathrm{red}$"
ZOOM_SD = 6.0  # half-width of the zoomed posterior panel, in posterior standard deviations
HEATMAP_COLORS = matplotlib.colormaps["viridis"].with_extremes(bad="lightgrey")  # NaN cells grey
# A log axis over more decades than this draws no minor ticks: there they are a smear, eight to a decade, and their
# artists cost more to lay out and draw than the rest of a spectrum's panel.
LOG_MINOR_DECADES = 4.0


def save(fig: Figure, png_path: PathLike, code_hash: str = "", sources: Sequence[PathLike] = ()) -> None:
    """Write ``fig`` to ``png_path`` and to the PDF of the same stem, with provenance in the metadata."""
    png_path = Path(png_path)
    if png_path.suffix != ".png":
        raise ValueError(f"figure path must end in .png, got {png_path}")
    stamp = {**provenance.attributes(code_hash), "sources": json.dumps([os.fspath(s) for s in sources])}
    # PDF metadata takes only its standard keys: the stamp goes into Subject as JSON.  Without a
    # CreationDate a rerun writes the same bytes.
    pdf_metadata = {"Creator": f"newdyn {stamp['newdyn_version']}", "Subject": json.dumps(stamp), "CreationDate": None}
    _thin_log_minor_ticks(fig)
    # A figure keeps its own layout whatever engine a user's matplotlibrc asks for by default.
    with matplotlib.rc_context({"figure.autolayout": False, "figure.constrained_layout.use": False}):
        _lay_out_once(fig)
        io.atomic_write(png_path, lambda tmp: fig.savefig(tmp, format="png", dpi=PNG_DPI, metadata=stamp))
        io.atomic_write(png_path.with_suffix(".pdf"), lambda tmp: fig.savefig(tmp, format="pdf", metadata=pdf_metadata))


def _lay_out_once(fig: Figure) -> None:
    """Run ``fig``'s layout engine once, at the PNG's resolution as savefig would, and keep that layout for both files.

    With an engine set, savefig draws the whole figure once more before each file only to lay it out; without one it
    draws each file once, and the files are the same bytes.  The layout runs on the Agg canvas that then draws the PNG,
    whose renderer keeps the text extents the layout measured."""
    engine = fig.get_layout_engine()
    if engine is None:
        return
    dpi = fig.get_dpi()
    fig.set_dpi(PNG_DPI)
    FigureCanvasAgg(fig)
    engine.execute(fig)
    fig.set_dpi(dpi)
    fig.set_layout_engine(None)  # no engine: the rc that save() sets asks for none by default


def _thin_log_minor_ticks(fig) -> None:
    """No minor ticks on a log axis of ``fig`` (its subfigures' too) that spans more than :data:`LOG_MINOR_DECADES`."""
    for ax in fig.get_axes() + [a for sub in fig.subfigs for a in sub.get_axes()]:
        for axis, (low, high) in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
            if axis.get_scale() == "log" and abs(math.log10(high / low)) > LOG_MINOR_DECADES:
                axis.set_minor_locator(NullLocator())


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
    """One block per posterior file (e.g. the 1-D and joint calibrations of one measurement): for an MCMC run, trace,
    marginal density and rank plots of every variable, titled with R-hat and ESS and, in red, why it did not
    converge; for a verified quadrature or importance-sampled answer (:mod:`newdyn.posterior`), each variable's
    marginal with its 94 % HDI, the weights of the points it was computed from, and its draws against the next
    variable's, titled with how it was verified."""
    import arviz as az  # slow to import: only this figure needs it

    from . import sampling

    runs = [sampling.load(path) for path in mcmc_paths]
    sizes = [len(idata.posterior.data_vars) for idata in runs]
    fig = Figure(figsize=(14, 1.2 * len(runs) + 2.6 * sum(sizes)), layout="constrained")
    for block, idata in zip(np.atleast_1d(fig.subfigures(len(runs), 1, height_ratios=sizes)), runs):
        attrs = idata.attrs  # netCDF attributes come back as text
        names = list(idata.posterior.data_vars)
        axes = block.subplots(len(names), 3, squeeze=False)
        converged = bool(int(float(attrs["converged"])))
        if attrs.get("method", "mcmc") == "mcmc":
            az.plot_trace(idata, var_names=names, axes=axes[:, :2])
            # Each walker's count per rank bin against the uniform count: a row of bars per walker is unreadable
            # with 16-32 walkers, and its thousands of patches took 40 % of the figure's time.
            az.plot_rank(idata, var_names=names, ax=axes[:, 2], kind="vlines")
            title = (f"MCMC {', '.join(names)}: {_subject(attrs)}\n"
                     f"R-hat = {float(attrs['rhat']):.4f}, ESS bulk = {float(attrs['ess_bulk']):.0f}")
        else:
            weights = np.exp(idata["weighted"]["log_weight"].values)
            for row, name in zip(axes, names):
                az.plot_posterior(idata, var_names=[name], ax=row[0], hdi_prob=0.94, textsize=9)
                row[1].plot(idata["weighted"][name].values, weights, ".", markersize=2)
                row[1].set(xlabel=name, ylabel="weight")
                other = names[(names.index(name) + 1) % len(names)]
                row[2].plot(idata.posterior[name].values.ravel(), idata.posterior[other].values.ravel(), ".", markersize=1, alpha=0.3)
                row[2].set(xlabel=name, ylabel=other)
            title = f"{', '.join(names)}: {_subject(attrs)}\n{_verification(attrs)}"
        if not converged:
            title += f"\n{'UNCONVERGED' if attrs.get('method', 'mcmc') == 'mcmc' else 'UNVERIFIED'}: {attrs['reason']}"
        block.suptitle(title, color="black" if converged else MARK_COLOR, fontweight="normal" if converged else "bold")
    save(fig, png_path, code_hash, mcmc_paths)
    return fig


def _verification(attrs) -> str:
    """How a posterior of :mod:`newdyn.posterior` was computed and verified, in one line."""
    if "pareto_k" in attrs:
        refitted = f", the proposal fitted again {int(attrs['refits'])}x" if int(attrs["refits"]) else ""
        return (f"{attrs['method']}: Pareto k = {float(attrs['pareto_k']):.2f}, ESS = {float(attrs['ess_bulk']):.0f} "
                f"of {int(attrs['n_proposals'])} proposals{refitted}")
    return f"{attrs['method']}: {int(attrs['n_points'])} lattice points, step {float(attrs['step']):g} sd of the Laplace approximation"


def model_overlays(
    measurement_path: PathLike,
    grid_result_paths: Sequence[PathLike],
    png_path: PathLike,
    window: float = 0.2,
    code_hash: str = "",
) -> Figure:
    """Where the best-fitting models fail: per channel, data and best fits over the first ``window``
    seconds (left), and the PSD of the data and of each fit's residual against the noise floor (right)."""
    measurement = io.read_measurement(measurement_path, warm_up=None)  # a study simulation, on the model's clock
    results = [_load(path) for path in grid_result_paths]
    times, fs = measurement.sampling.times, measurement.sampling.fs
    for path, result in zip(grid_result_paths, results):
        missing = set(result["channel"].values) - set(measurement.channels)
        if missing:
            raise ValueError(f"{path}: channels {sorted(missing)} are not in {measurement_path}")
        if not np.allclose(result["time"].values, times, rtol=0.0, atol=io.TIME_JITTER / fs):
            raise ValueError(f"{path}: best fit is not sampled at the times of {measurement_path}")
    channels = list(dict.fromkeys(str(c) for result in results for c in result["channel"].values))
    fits = {
        channel: [
            (f"{r.attrs['parameter']} best fit ({CHI2_RED} = {float(r.attrs['chi2_red']):.3g})",
             f"data − {r.attrs['parameter']} best fit", r["best_fit"].sel(channel=channel).values)
            for r in results if channel in r["channel"]
        ]
        for channel in channels
    }
    rows = [measurement.channels.index(c) for c in channels]
    fig = _overlay_grid(
        channels, times, fs, dict(zip(channels, measurement.y[rows])), fits,
        dict(zip(channels, measurement.sigma[rows])) if measurement.sigma is not None else {}, window,
        f"Best-fitting models against {_subject({**measurement.attrs, 'measurement': measurement.name})}",
    )
    save(fig, png_path, code_hash, [measurement_path, *grid_result_paths])
    return fig


def diagnosis_figures(verdict_path: PathLike, diagnosis_path: PathLike, posterior_path: PathLike, png_paths: dict,
                      code_hash: str = "") -> None:
    """The figures of one diagnosis: ``png_paths`` maps overlays, residuals, hypotheses, error_fall,
    discovery and effect_posterior to their PNG paths."""
    with open(verdict_path) as f:
        verdict = json.load(f)
    result = _load(diagnosis_path)
    sources = [verdict_path, diagnosis_path]
    name = verdict["measurement"]
    diagnosis_overlays(verdict, result, png_paths["overlays"], code_hash, sources)
    channels = list(result["channel"].values)
    colour = noise.Colour.from_summary(verdict["noise"].get("colour", {}), channels)  # as the verdict judged it
    residual, sigma_e, times = colour.seen(result["y"].values - result["model"].sel(version="calibrated").values,
                                           result["sigma"].values, result["time"].values)
    residual_map(residual, sigma_e, channels, times, float(result.attrs["fs"]), float(result.attrs["load_freq"]), png_paths["residuals"],
                 f"{name}: where the calibrated model ({verdict['models']['calibrated']}) fails"
                 + (", noise whitened" if colour.order else ""), code_hash, sources)
    hypothesis_ranking(verdict, result, png_paths["hypotheses"], code_hash, sources)
    error_fall(verdict, result, png_paths["error_fall"], code_hash, sources)
    discovered_force(verdict, result, png_paths["discovery"], code_hash, sources)
    effect_posterior(posterior_path, png_paths["effect_posterior"], code_hash)


def effect_posterior(posterior_path: PathLike, png_path: PathLike, code_hash: str = "") -> Figure:
    """The fault model's posterior: MCMC's diagnostics (:func:`mcmc_diagnostics`) where it was sampled by MCMC, else
    its draws' marginals and pairs, titled with how they were verified (Pareto k̂ and the effective sample size of
    importance sampling, or quadrature's lattice step)."""
    import arviz as az  # slow to import: only this figure needs it

    from . import sampling

    idata = sampling.load(posterior_path)
    attrs = idata.attrs
    if attrs.get("method") == "mcmc":
        return mcmc_diagnostics([posterior_path], png_path, code_hash)
    names = list(idata.posterior.data_vars)
    size = max(2.6 * len(names) + 1, 6.0)
    fig = Figure(figsize=(size, size), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(names), len(names), squeeze=False))
    if len(names) > 1:
        az.plot_pair(idata, var_names=names, kind="kde", marginals=True, ax=axes)
    else:
        az.plot_posterior(idata, var_names=names, ax=axes[0, 0], hdi_prob=0.94)
    verified = bool(int(float(attrs["converged"])))
    title = f"posterior of {attrs['hypothesis']}\n{_verification(attrs)}"
    if not verified:
        title += f"\nUNVERIFIED: {attrs['reason']}"
    fig.suptitle(title, color="black" if verified else MARK_COLOR, fontweight="normal" if verified else "bold")
    save(fig, png_path, code_hash, [posterior_path])
    return fig


def _version_label(verdict: dict, version: str) -> str:
    hypothesis = verdict["models"][version]
    row = next(r for r in verdict["ranking"] if r["hypothesis"] == hypothesis)
    return f"{version} ({hypothesis}, {CHI2_RED} = {row['chi2']:.3g})"


def diagnosis_overlays(verdict: dict, result: xr.Dataset, png_path: PathLike, code_hash: str = "", sources=(), window: float = 0.2) -> Figure:
    """Per channel: the data and the model versions nominal, calibrated and + effect over the first
    ``window`` seconds (left), and the PSD of the data and of each version's residual against the
    noise floor (right)."""
    times, fs = result["time"].values, float(result.attrs["fs"])
    channels = [str(c) for c in result["channel"].values]
    fits = {
        channel: [(_version_label(verdict, version), f"residual, {version}",
                   result["model"].sel(version=version, channel=channel).values)
                  for version in ("nominal", "calibrated", "effect")]
        for channel in channels
    }
    fig = _overlay_grid(
        channels, times, fs, {c: result["y"].sel(channel=c).values for c in channels}, fits,
        {c: float(result["sigma"].sel(channel=c)) for c in channels}, window,
        f"{verdict['measurement']}: the model versions against the data",
    )
    save(fig, png_path, code_hash, sources)
    return fig


_CLASS_COLORS = {"healthy": "tab:green", "parameter_change": "tab:blue", "new_dynamics": "tab:red"}


def hypothesis_ranking(verdict: dict, result: xr.Dataset, png_path: PathLike, code_hash: str = "", sources=()) -> Figure:
    """Left: every hypothesis's log-evidence below the best's (the ranking), with its χ² and
    confidence.  Right: the Hellinger distances between the measurement's posteriors and each noise-free
    signature (the paper's Step 3), one row per signature."""
    ranking = verdict["ranking"]
    fig = Figure(figsize=(15, 0.8 + 0.32 * max(len(ranking), result.sizes["signature"] / 2)), layout="constrained")
    left, right = fig.subplots(1, 2, width_ratios=(1, 1.3))
    best = ranking[0]["log_evidence"]
    gaps = np.array([max(best - r["log_evidence"], 0.0) + 1.0 for r in ranking])
    rows = np.arange(len(ranking))
    left.barh(rows, gaps, color=[_CLASS_COLORS[r["class"]] for r in ranking], log=True)
    left.set_yticks(rows, [r["hypothesis"] for r in ranking])
    left.invert_yaxis()
    for row, r, gap in zip(rows, ranking, gaps):
        mark = "" if r["explains"] else "  (does not explain)"
        left.text(gap, row, f" {CHI2_RED}={r['chi2']:.3g}, p={r['confidence']:.2g}{mark}", va="center", fontsize="small")
    left.set_xlabel("1 + log-evidence below the best hypothesis (log scale)")
    left.set_title(f"Verdict: {verdict['verdict']}" + (f" ({verdict['effect']})" if verdict["effect"] else ""))
    distances = result["hellinger"]
    _draw_heatmap(fig, right, distances.values, [str(s) for s in distances["signature"].values],
                  [str(p) for p in distances["parameter"].values], "Hellinger distance to each signature's posterior",
                  "H", limits=(0.0, 1.0))
    save(fig, png_path, code_hash, sources)
    return fig


def discovered_force(verdict: dict, result: xr.Dataset, png_path: PathLike, code_hash: str = "", sources=()) -> Figure:
    """The missing force that discovery estimated where its best candidate acts, over the record: in time
    (posterior mean ± 2 sd), as a spectrum, against the disk's angle and against the load-cycle phase; a
    note instead when discovery did not run."""
    discovery = verdict.get("discovery") or {}
    if "force_mean" not in result or not discovery.get("candidates"):
        fig = Figure(figsize=(15, 7.5))  # a note alone: no axes for a layout engine to place (it would warn)
        fig.text(0.5, 0.5, f"{verdict['measurement']}: verdict {verdict['verdict']}, no discovery "
                 "(it runs when nothing of the library explains the data, or with diagnosis.discovery: always)",
                 ha="center", va="center")
        save(fig, png_path, code_hash, sources)
        return fig
    fig = Figure(figsize=(15, 7.5), layout="constrained")
    best = discovery["candidates"][0]
    place = best["acts_on"]
    times = result["pulse_time"].values
    record = times >= float(result["time"].values[0])
    mean, sd = (result[name].sel(place=place).values[record] for name in ("force_mean", "force_sd"))
    t = times[record]
    unit = next(iter(best["parameters"].values()))["unit"] if best["parameters"] else ""
    time_ax, spectrum_ax, angle_ax, phase_ax = fig.subplots(2, 2).ravel()
    time_ax.fill_between(t, mean - 2 * sd, mean + 2 * sd, color="tab:blue", alpha=0.25, lw=0, label="± 2 sd")
    time_ax.plot(t, mean, lw=0.7, color="tab:blue", label="posterior mean")
    time_ax.set_xlabel("time [s]")
    time_ax.set_ylabel(f"force on {place}")
    time_ax.legend(fontsize="small")
    step = float(t[1] - t[0])
    frequency = np.fft.rfftfreq(t.size, step)
    amplitude = np.abs(np.fft.rfft(mean - mean.mean()))[1:] * 2 / t.size  # without the mean, whose place the calibration took
    spectrum_ax.semilogy(frequency[1:], amplitude, lw=0.7)
    spectrum_ax.axhline(2 * np.sqrt(np.mean(sd**2) / t.size), color="grey", ls="--", label="uncertainty of one line")
    if best["frequency_hz"]:
        spectrum_ax.axvline(best["frequency_hz"], color=MARK_COLOR, ls=":", label=f"{best['term']} {best['shape']}")
    spectrum_ax.set_xlabel("frequency [Hz]")
    spectrum_ax.set_ylabel("amplitude")
    spectrum_ax.legend(fontsize="small")
    disk = "4" if "disk 4" in best["shape"] else "1"
    angle = np.mod(result[f"theta{disk}_at_pulse"].values[record], 2 * np.pi)
    angle_ax.plot(angle, mean, ".", ms=2)
    angle_ax.set_xlabel(f"angle of disk {disk} [rad]")
    angle_ax.set_ylabel(f"force on {place}")
    phase_ax.plot(np.mod(t * float(result.attrs["load_freq"]), 1.0), mean, ".", ms=2)
    phase_ax.set_xlabel("load-cycle phase")
    phase_ax.set_ylabel(f"force on {place}")
    fig.suptitle(f"{verdict['measurement']}: the missing force on {place} estimated from the residual of "
                 f"{discovery['from']}; best form {best['term']} ({best['shape']}){f' [{unit}]' if unit else ''}")
    save(fig, png_path, code_hash, sources)
    return fig


def error_fall(verdict: dict, result: xr.Dataset, png_path: PathLike, code_hash: str = "", sources=()) -> Figure:
    """The error falling over the model versions, nominal → calibrated → best library effect (→ the
    discovered term): reduced χ² (left), RMSE per channel relative to the noise σ (middle), and the
    residual spectra of the nominal model and the final one (right)."""
    versions = [v for v in ("nominal", "calibrated", "effect", "discovered") if v in verdict["models"]]
    rows = {r["hypothesis"]: r for r in (*verdict["ranking"], *verdict["model_versions"])}
    channels = [str(c) for c in result["channel"].values]
    sigma = result["sigma"].values
    fs = float(result.attrs["fs"])
    fig = Figure(figsize=(15, 4.5), layout="constrained")
    chi_ax, rmse_ax, psd_ax = fig.subplots(1, 3)
    chi2 = [rows[verdict["models"][v]]["chi2"] for v in versions]
    labels = [f"{v}\n{verdict['models'][v]}" for v in versions]
    chi_ax.bar(labels, chi2, color="tab:grey", log=True)
    chi_ax.axhline(float(verdict["settings"]["calibration"]["chi2_max"]), color=MARK_COLOR, ls="--", label="explains: χ² ≤ this")
    chi_ax.set_ylabel(CHI2_RED)
    chi_ax.legend(fontsize="small")
    width = 0.8 / len(channels)
    for i, channel in enumerate(channels):
        residual = result["y"].sel(channel=channel).values - result["model"].sel(channel=channel, version=list(versions)).values
        rmse = np.sqrt(np.mean(residual**2, axis=-1)) / sigma[i]
        rmse_ax.bar(np.arange(len(versions)) + i * width, rmse, width, label=channel)
    rmse_ax.set_xticks(np.arange(len(versions)) + width * (len(channels) - 1) / 2, labels)
    rmse_ax.set_yscale("log")
    rmse_ax.axhline(1.0, color="grey", ls="--", label="noise σ")
    rmse_ax.set_ylabel("RMSE / σ")
    rmse_ax.legend(fontsize="small")
    after = "discovered" if "discovered" in verdict["models"] else next(
        (v for v in versions if verdict["models"][v] == verdict["models"]["after"]), "effect")
    for i, channel in enumerate(channels):
        data = result["y"].sel(channel=channel).values
        for version, style in (("nominal", ":"), (after, "-")):
            frequency, density = _psd(data - result["model"].sel(channel=channel, version=version).values, fs)
            psd_ax.semilogy(frequency, density / (2 * sigma[i] ** 2 / fs), ls=style, lw=0.8, label=f"{channel}, {version}")
    psd_ax.axhline(1.0, color="grey", ls="--", label="noise floor")
    psd_ax.set_xlim(0, min(500.0, fs / 2))
    psd_ax.set_xlabel("frequency [Hz]")
    psd_ax.set_ylabel("residual PSD / noise floor")
    psd_ax.legend(fontsize="small")
    fig.suptitle(f"{verdict['measurement']}: {CHI2_RED} {verdict['chi2_before']:.3g} → {verdict['chi2_after']:.3g}")
    save(fig, png_path, code_hash, sources)
    return fig


def machine_verdict(verdict: dict, png_path: PathLike, code_hash: str = "", sources=()) -> Figure:
    """A machine's verdict (:func:`newdyn.machine.diagnose`): per recording the nominal and the final model's reduced χ²
    (left) and the expected log Bayes factor of the finding in it (middle, where it shows); right, where rivals remain,
    the expected log Bayes factor a recording would give against each across the advised operating parameter."""
    lines = verdict["recordings"]
    names = [f"{line['name']}\n{', '.join(line['channels'])}" for line in lines]
    margin = float(verdict["settings"]["diagnosis"]["evidence_margin"])
    fig = Figure(figsize=(15, 4.5), layout="constrained")
    chi_ax, shows_ax, next_ax = fig.subplots(1, 3)
    x = np.arange(len(lines))
    chi_ax.bar(x - 0.2, [line["chi2_before"] for line in lines], 0.4, color="tab:grey", log=True, label="nominal")
    chi_ax.bar(x + 0.2, [line["chi2_after"] for line in lines], 0.4, color="tab:blue", log=True, label=verdict["model"])
    chi_ax.axhline(float(verdict["settings"]["calibration"]["chi2_max"]), color=MARK_COLOR, ls="--", label="explains: χ² ≤ this")
    chi_ax.set_xticks(x, names)
    chi_ax.set_ylabel(CHI2_RED)
    chi_ax.legend(fontsize="small")
    shows_ax.bar(x, [max(line["finding_log_bayes_factor"], 1e-3) for line in lines], color="tab:blue", log=True)
    shows_ax.axhline(margin, color=MARK_COLOR, ls="--", label="visible above this")
    shows_ax.set_xticks(x, names)
    shows_ax.set_ylabel("expected log Bayes factor of the finding")
    shows_ax.legend(fontsize="small")
    advice = verdict.get("record_next")
    if advice:
        for row in advice["rivals"]:
            moved = [c for c in row["candidates"] if c["parameter"] == row["advice"]["parameter"]]
            next_ax.semilogy([c["value"] for c in moved], [max(c["expected_log_bayes_factor"], 1e-3) for c in moved],
                             marker="o", label=f"{row['rival']} ({row['advice']['parameter']})")
        next_ax.axhline(margin, color=MARK_COLOR, ls="--", label="tells apart above this")
        next_ax.set_xlabel("operating value of a next recording (the rest as in the first)")
        next_ax.set_ylabel(f"expected log Bayes factor against {advice['model']}")
        next_ax.legend(fontsize="small")
    else:
        next_ax.set_axis_off()
        next_ax.text(0.5, 0.5, "no rival left: nothing to record next", ha="center", va="center", transform=next_ax.transAxes)
    fig.suptitle(f"machine {verdict['machine']}: {verdict['verdict']}" + (f" ({verdict['effect']})" if verdict["effect"] else ""))
    save(fig, png_path, code_hash, sources)
    return fig


def _overlay_grid(channels, times, fs, data, fits, sigma, window, title) -> Figure:
    """Per channel (rows): the data and each fit over the first ``window`` seconds (left), and the PSD
    of the data and of each fit's residual against the noise floor 2σ²/fs where σ is known (right).
    ``fits`` maps a channel to (label, residual label, fit) triples; ``sigma`` a channel to its σ."""
    fig = Figure(figsize=(14, 0.8 + 3.0 * len(channels)), layout="constrained")
    axes = fig.subplots(len(channels), 2, squeeze=False)
    shown = times < times[0] + window
    for (signal_ax, psd_ax), channel in zip(axes, channels):
        signal_ax.plot(times[shown], data[channel][shown], color="black", lw=0.8, label="data")
        psd_ax.semilogy(*_psd(data[channel], fs), color="black", lw=0.8, label="data")
        for label, residual_label, fit in fits[channel]:
            (line,) = signal_ax.plot(times[shown], fit[shown], lw=0.8, label=label)
            psd_ax.semilogy(*_psd(data[channel] - fit, fs), color=line.get_color(), lw=0.8, label=residual_label)
        if channel in sigma:
            psd_ax.axhline(2 * sigma[channel] ** 2 / fs, color="grey", ls="--", label="noise floor 2σ²/fs")
        unit = model.CHANNEL_UNITS[channel]
        signal_ax.set_ylabel(f"{channel} [{unit}]")
        psd_ax.set_ylabel(f"PSD [{unit}²/Hz]")
    for ax in axes[0]:
        ax.legend(loc="upper right", fontsize="small")
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("frequency [Hz]")
    fig.suptitle(title)
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


def residual_map(
    residual: np.ndarray,
    sigma: np.ndarray,
    channels: Sequence[str],
    times: np.ndarray,
    fs: float,
    load_freq: float,
    png_path: PathLike,
    title: str,
    code_hash: str = "",
    sources: Sequence[PathLike] = (),
) -> Figure:
    """Where a model fails, per channel (rows): the residual's time-frequency map in dB above the
    white-noise floor up to 500 Hz (left), and its mean (r/σ)² per load-cycle phase bin against the
    null's central 99.9 % (right).  Findings of :func:`newdyn.residuals.where_it_fails` are marked red."""
    frequency, map_times, power = residuals.time_frequency_map(residual, sigma, fs, t_first=float(times[0]))
    phase = residuals.phase_excess(residual, sigma, times, load_freq)
    lower, upper = residuals.phase_null_band(phase.counts)
    findings = residuals.where_it_fails(residual, sigma, channels, times, fs, load_freq)
    f_max = min(500.0, fs / 2)
    shown = frequency <= f_max
    fig = Figure(figsize=(13, 0.8 + 2.8 * len(channels)), layout="constrained")
    axes = fig.subplots(len(channels), 2, squeeze=False, width_ratios=(3, 2))
    for c, ((map_ax, phase_ax), channel) in enumerate(zip(axes, channels)):
        # A single cell of pure noise is χ²₂/2, so half of them lie below 0 dB: the scale starts at the floor.
        mesh = map_ax.pcolormesh(
            map_times, frequency[shown], 10 * np.log10(power[c, shown]), shading="nearest", cmap="magma", vmin=0.0,
            vmax=30.0,
        )
        map_ax.set_ylim(0.0, f_max)
        map_ax.set_ylabel(f"{channel}\nfrequency [Hz]")
        phase_ax.stairs(upper, phase.edges, baseline=lower, fill=True, color="lightgrey", label="null, central 99.9 %")
        phase_ax.stairs(phase.excess[c], phase.edges, color="black", label="data − model")
        phase_ax.axhline(1.0, color="grey", ls="--", lw=0.8)
        phase_ax.set_xlim(0.0, 1.0)
        phase_ax.set_yscale("log")  # an excess may be thousands, while the null band hugs 1
        phase_ax.set_ylabel(r"mean $(r/\sigma)^2$")
        flagged = []
        for finding in (f for f in findings if f["channel"] == channel):
            if finding["kind"] == "band":
                flagged.append(f"{finding['low_hz']:g}–{finding['high_hz']:g} Hz ×{finding['excess']:.2g}")
                if finding["low_hz"] < f_max:  # a bar at the right edge, so the map stays visible
                    map_ax.axhspan(finding["low_hz"], min(finding["high_hz"], f_max), xmin=0.98, color=MARK_COLOR)
            else:
                low, high = finding["phase_low"], finding["phase_high"]
                # A window across phase 1 → 0 is drawn in two parts.
                for a, b in ((low, min(high, 1.0)), (0.0, high - 1.0)):
                    if b > a:
                        phase_ax.axvspan(a, b, color=MARK_COLOR, alpha=0.2)
        # The three largest by name: the red bars on the map show the rest below 500 Hz.
        shown_flags = ", ".join(flagged[:3]) + (f" and {len(flagged) - 3} more" if len(flagged) > 3 else "")
        map_ax.set_title(
            f"above the noise floor: {shown_flags}" if flagged else "no band above the noise floor",
            color=MARK_COLOR if flagged else "black", fontsize="small",
        )
    fig.colorbar(mesh, ax=axes[:, 0], label="power above the noise floor [dB]", extend="both")
    axes[0, 1].legend(loc="upper right", fontsize="small")
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel(f"load-cycle phase (t · {load_freq:g} Hz) mod 1")
    fig.suptitle(title)
    save(fig, png_path, code_hash, sources)
    return fig


def blind_test_figure(
    score: dict, png_path: PathLike, title: str, code_hash: str = "", sources: Sequence[PathLike] = ()
) -> Figure:
    """A blind test's score (:func:`newdyn.hidden.score`): left the confusion matrix, truth class ×
    predicted label, with the count in each cell and the correct cells framed (a parameter-change
    cell also says how many named the right parameter); right the relative error of each fitted
    parameter of the correctly identified cases with its 94 % HDI as a bar, green when the HDI covers
    the truth, red when not.  The title gives the top-1 accuracy."""
    from matplotlib.ticker import MaxNLocator

    confusion = score["confusion"]
    truth, predicted = list(confusion["truth"]), list(confusion["predicted"])
    counts = np.asarray(confusion["counts"], dtype=int).reshape(len(truth), len(predicted))
    errors = [e for e in score["parameter_errors"] if e.get("relative_error") is not None]
    height = max(4.5, 1.8 + 0.5 * len(truth), 1.5 + 0.28 * len(errors))
    fig = Figure(figsize=(14, height), layout="constrained")
    matrix_ax, error_ax = fig.subplots(1, 2, width_ratios=(1.2, 1))

    image = matrix_ax.imshow(counts, cmap="Blues", vmin=0, vmax=max(1, int(counts.max())), aspect="auto")
    fig.colorbar(image, ax=matrix_ax, label="cases", ticks=MaxNLocator(integer=True))
    per_class = score["per_class"]
    matrix_ax.set_yticks(range(len(truth)), [f"{c} ({per_class[c]['correct']}/{per_class[c]['cases']})" for c in truth])
    matrix_ax.set_xticks(range(len(predicted)), predicted, rotation=45, ha="right", rotation_mode="anchor")
    right_parameter = sum(1 for row in score["rows"] if row["class"] == "parameter_change" and row["correct"])
    for (i, j), count in np.ndenumerate(counts):
        text = str(count)
        if truth[i] == predicted[j] == "parameter_change" and right_parameter != count:
            text += f"\n({right_parameter} right)"
        dark = count > 0.6 * max(1, counts.max())
        matrix_ax.text(j, i, text, ha="center", va="center", fontsize="small" if "\n" in text else "medium",
                       color="white" if dark else ("black" if count else "lightgrey"))
        if truth[i] == predicted[j]:
            matrix_ax.add_patch(Rectangle((j - 0.45, i - 0.45), 0.9, 0.9, fill=False, edgecolor="tab:green", lw=2.5))
    matrix_ax.set_xlabel("predicted (green frame: correct)")
    matrix_ax.set_ylabel("truth (correct / cases)")
    matrix_ax.set_title("confusion matrix")

    fit = score.get("fault_fit") or {}
    if errors:
        y = np.arange(len(errors))
        for k, e in enumerate(errors):
            scale = abs(e["truth"])
            color = {True: "tab:green", False: MARK_COLOR, None: "grey"}[e.get("in_hdi")]
            xerr = None
            if e.get("hdi_low") is not None and e.get("hdi_high") is not None:
                low, high = (e["hdi_low"] - e["truth"]) / scale, (e["hdi_high"] - e["truth"]) / scale
                xerr = [[max(0.0, e["relative_error"] - low)], [max(0.0, high - e["relative_error"])]]
            error_ax.errorbar(e["relative_error"], k, xerr=xerr, fmt="o", color=color, capsize=3,
                              mfc=color if e.get("in_hdi") else "white")
        error_ax.set_yticks(y, [f"{e['case']}: {e['parameter']}" for e in errors])
        error_ax.invert_yaxis()
        error_ax.axvline(0.0, color="black", lw=0.8)
        error_ax.set_xscale("symlog", linthresh=1e-3, linscale=0.5)
        covered = [e["in_hdi"] for e in errors if e.get("in_hdi") is not None]
        coverage = f"truth in 94 % HDI: {sum(covered)}/{len(covered)}" if covered else "no HDIs"
    else:
        error_ax.text(0.5, 0.5, "no fitted parameters of correctly identified cases", ha="center", va="center",
                      transform=error_ax.transAxes)
        error_ax.set_yticks([])
        coverage = "no HDIs"
    error_ax.set_xlabel("relative error (fitted mean − true) / |true|; bar: 94 % HDI")
    explained = f"\ncorrect fault fits with {CHI2_RED} ≤ {fit['chi2_max']:g}: {fit['explained']}/{fit['cases']}" if fit.get("cases") else ""
    error_ax.set_title(f"fitted parameters of correct cases ({coverage}){explained}", fontsize="medium")
    accuracy = score["accuracy"]
    fig.suptitle(f"{title}: top-1 accuracy {accuracy:.0%} ({score['correct']}/{score['cases']})"
                 if accuracy is not None else f"{title}: no cases")
    save(fig, png_path, code_hash, sources)
    return fig
