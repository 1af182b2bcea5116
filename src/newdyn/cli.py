"""``newdyn`` command line: one subcommand per workflow stage, each a thin call into the package.

Snakemake rules run these as shell commands so every job is its own process (its thread count
honoured, runnable on a cluster through Snakemake's executor plugins).  A user runs ``newdyn check``
(measurement files) and ``newdyn check-config`` by hand.  A bad file, config or path given to any
command ends it with one line on stderr naming the file and the problem, and exit status 1.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import json
import logging
import sys
import time
from pathlib import Path

# The process ends with its outputs written: its last garbage collection, through every object the libraries made,
# would only delay the job's end (and the next job's start).
atexit.register(gc.freeze)

log = logging.getLogger("newdyn")
DIAGNOSIS_FIGURES = ("overlays", "residuals", "hypotheses", "error_fall", "discovery", "effect_posterior")
DEFAULT_CONFIG = "config/config.yaml"  # the workflow's configfile, in the directory it runs in


def check_measurements(paths: list[str], config_paths: list[str]) -> int:
    """Print one line per measurement file of ``paths`` (files, or folders as the workflow lists measurements/ and a
    machine's folder): OK with what the diagnosis will use, or its problem as the workflow would skip it; checked against
    the config of ``config_paths`` merged in order.  Returns the exit status: 1 if a file is bad, else 0."""
    from . import catalog, io

    study = _merged_config(config_paths)
    operating, channels = study["operating"], study["diagnosis"]["channels"]
    band_hz = study["diagnosis"]["noise_band_hz"]
    bad = 0
    for path in map(Path, paths):
        if path.is_dir():
            good, problems = catalog.good_measurements(path, operating, channels, band_hz, index=None, rig=study["rig"])
            if not good and not problems:
                problems = [f"{path}: holds no measurement file (.nc or .csv), nor a machine's folder of them"]
            found = [(str(file), None) for file in good.values()] + [(line.split(": ", 1)[0], line) for line in problems]
        else:
            found = [(str(path), catalog.name_problem(path, path.stem))]
        for file, problem in sorted(found):
            if problem is None:
                try:
                    print(_measurement_summary(catalog.checked_measurement(file, operating, channels, band_hz, study["rig"]), file,
                                               channels, band_hz))
                    continue
                except io.MeasurementError as error:
                    problem = str(error)
            print(problem)
            bad += 1
    return 1 if bad else 0


def _measurement_summary(measurement, path: str, channels: list[str], band_hz: float) -> str:
    """``<path>: OK: …``, what a diagnosis of ``measurement`` uses: its channels, sampling, noise level and condition."""
    from . import measurement_checks

    used = measurement_checks.present_channels(measurement, channels)
    _, noise_source = measurement_checks.noise_level(measurement, [measurement.channels.index(c) for c in used], band_hz)
    missing = [c for c in channels if c not in used]
    sampling = measurement.sampling
    return (f"{path}: OK: channels {', '.join(measurement.channels)}, diagnosed on {', '.join(used)}"
            + (f" (without {', '.join(missing)} of diagnosis.channels)" if missing else "")
            + f"; {sampling.fs:.6g} Hz, {sampling.n_samples} samples, {sampling.n_samples / sampling.fs:.6g} s; noise level "
              f"from {noise_source}; operating condition "
            + ", ".join(f"{name} {value:g}" for name, value in measurement.operating.items()))


def check_config(paths: list[str]) -> None:
    """Print ``<files>: OK`` when the config files ``paths``, merged in order, make a good study (else
    :class:`newdyn.config.ConfigError` names the files, the field and the problem)."""
    _merged_config(paths)
    print(f"{', '.join(paths)}: OK")


def _merged_config(paths: list[str]) -> dict:
    """:func:`newdyn.config.load_merged` of ``paths``; where they lack a required key and leave out the default config
    that is there, the line says how to check them as ``snakemake --configfile`` takes them: merged over the default."""
    from . import config

    try:
        return config.load_merged(paths)
    except config.ConfigError as error:
        default = Path(DEFAULT_CONFIG).resolve()
        if (error.problem.startswith(config.MISSING_KEY) and default.is_file()
                and default not in {Path(path).resolve() for path in paths}):
            raise config.ConfigError(error.source, error.field, f"{error.problem}; to check an override as snakemake "
                                     f"--configfile takes it, merged over the default, give {DEFAULT_CONFIG} first") from None
        raise


def simulate_scenario(spec: dict, output: str, code_hash: str) -> None:
    """Write the clean simulated measurement of one scenario (spec built by the workflow)."""
    from . import io, provenance, simulation

    sampling = _sampling(spec["sampling"])
    values = spec["values"]
    start = time.perf_counter()
    y = simulation.simulate(values, sampling, spec["channels"], spec["max_step"])
    log.info("simulated %s: %d channels x %d samples in %.2f s", spec["scenario"], len(spec["channels"]),
             sampling.n_samples, time.perf_counter() - start)
    attrs = {
        "title": f"newdyn simulation of scenario {spec['scenario']} (clean)",
        "scenario": spec["scenario"],
        "variant": spec["variant"],
        "scenario_definition": spec["definition"],
        "fault": spec["definition"].get("fault", {}).get("kind", "none"),
        "parameters": values,
        "max_step": spec["max_step"],
        **provenance.attributes(code_hash),
    }
    io.write_netcdf(io.measurement_dataset(y, spec["channels"], sampling, values, attrs), output)


def add_noise_to_file(source: str, output: str, snr_db: float, seed: int, code_hash: str) -> None:
    """Write a noisy copy of a clean measurement at ``snr_db`` with noise stream ``seed``."""
    import xarray as xr

    from . import io, noise, provenance

    with xr.open_dataset(source, engine="netcdf4") as clean:
        clean.load()
    channels = [str(c) for c in clean["channel"].values]
    noisy, sigma = noise.add_noise(clean["y"].values, channels, snr_db, seed)
    ds = clean.copy()
    ds["y"] = (("channel", "time"), noisy, clean["y"].attrs)
    ds = ds.assign_coords(sigma=("channel", sigma))
    ds["sigma"].attrs.update(long_name="noise standard deviation", units="channel units")
    ds.attrs.update(
        title=clean.attrs["title"].replace("(clean)", f"(SNR {snr_db:g} dB, seed {seed})"),
        snr_db=float(snr_db),
        seed=int(seed),
        **provenance.attributes(code_hash, hash_key="noise_code_hash"),  # keeps the simulation's code_hash
    )
    io.write_netcdf(ds, output)
    log.info("added noise at %g dB (seed %d): sigma %s", snr_db, seed, {c: float(f"{s:.4g}") for c, s in zip(channels, sigma)})


def simulate_grid_models(spec: dict, output: str, code_hash: str) -> None:
    """Write the coarse-grid model runs of one calibration parameter (independent of any data)."""
    import xarray as xr

    from . import calibration, io, model, provenance

    grid = calibration.GridSpec.from_config(spec["parameter"], spec["grid"])
    sampling = _sampling(spec["sampling"])
    start = time.perf_counter()
    models = calibration.simulate_grid(spec["values"], grid.parameter, grid.axis, sampling, spec["channels"], spec["max_step"])
    log.info("simulated %d grid points of %s in %.2f s", grid.points, grid.parameter, time.perf_counter() - start)
    ds = xr.Dataset(
        {"model": (("grid", "channel", "time"), models)},
        coords={"grid": grid.axis, "channel": spec["channels"], "time": sampling.times},
        attrs={
            "title": f"newdyn coarse likelihood grid of {grid.parameter}: healthy-rig model runs",
            "parameter": grid.parameter,
            "values": json.dumps(spec["values"], sort_keys=True),
            "max_step": spec["max_step"],
            **provenance.attributes(code_hash),
            **{name: float(spec["values"][name]) for name in model.OPERATING_PARAMETERS},
        },
    )
    io.write_netcdf(ds, output)


def calibrate_on_grids(measurement_path: str, grid_paths: list[str], spec: dict, outputs: list[str], code_hash: str) -> None:
    """Write the grid posterior of each parameter of ``spec["parameters"]`` for one measurement, with its summary as
    attributes: ``grid_paths`` and ``outputs`` are the parameters' coarse grids and result files, in that order.  One
    process calibrates them all, so that its start and imports are paid once per measurement."""
    entries = spec["parameters"]
    if not len(entries) == len(grid_paths) == len(outputs):
        raise ValueError(f"need a coarse grid and an output per parameter ({len(entries)}), got {len(grid_paths)} and {len(outputs)}")
    settings = {key: value for key, value in spec.items() if key != "parameters"}
    for entry, grid_path, output in zip(entries, grid_paths, outputs):
        calibrate_on_grid(measurement_path, grid_path, {**entry, **settings}, output, code_hash)


def calibrate_on_grid(measurement_path: str, grid_path: str, spec: dict, output: str, code_hash: str) -> None:
    """Write the grid posterior of one parameter for one measurement, with its summary as attributes (``spec``: its
    ``parameter``, ``prior`` and ``grid`` with the calibration settings, kept as the file's ``settings``)."""
    import xarray as xr

    from . import calibration, io, provenance

    channels = spec["channels"]
    measurement, data, sigma, values, grid, prior = _calibration_inputs(measurement_path, spec)

    coarse_models = calibration.coarse_models(grid_path, grid, values, measurement.sampling, channels, spec["max_step"])
    result = calibration.calibrate(
        data, sigma, grid, prior, coarse_models, values, measurement.sampling, channels,
        int(spec["refine_points"]), spec["chi2_max"], spec["max_step"],
    )
    post = result.posterior
    summary = result.summary()
    log.info("%s on %s: %s", grid.parameter, measurement.name, summary)
    ds = xr.Dataset(
        {
            "posterior": ("grid", post.density),
            "log_likelihood": ("grid", post.log_likelihood),
            "scaled_likelihood": ("grid", post.scaled_likelihood),
            "prior": ("grid", post.prior_density),
            "best_fit": (("channel", "time"), result.best_fit),
        },
        coords={"grid": post.grid, "channel": channels, "time": measurement.sampling.times},
        attrs={
            "title": f"newdyn grid calibration of {grid.parameter} on {measurement.name}",
            **_labels(measurement),
            "parameter": grid.parameter,
            "true_value": _true_value(measurement, grid.parameter),
            "method": "grid",
            **summary,
            "settings": json.dumps(spec, sort_keys=True),
            **provenance.attributes(code_hash),
        },
    )
    io.write_netcdf(ds, output)


def calibrate_by_mcmc(measurement_path: str, grid_result_paths: list[str], runs: list[dict], outputs: list[str],
                      code_hash: str) -> None:
    """Run a measurement's MCMC calibrations one after the other, in one process: each run (``name`` a parameter, or
    ``joint``, and its ``spec``) writes its posterior to the output of the same place; the grid calibrations that start
    the walkers are matched by the parameter each file says it holds."""
    from . import calibration

    if len(outputs) != len(runs):
        raise ValueError(f"need one output per run ({', '.join(run['name'] for run in runs)}), got {len(outputs)}")
    grid_results = calibration.grid_files(grid_result_paths)
    for run, output in zip(runs, outputs):
        needed = list(run["spec"]["parameters"]) if run["name"] == "joint" else [run["name"]]
        missing = [name for name in needed if name not in grid_results]
        if missing:
            raise ValueError(f"no grid calibration of {', '.join(missing)} among {', '.join(grid_result_paths)}")
        if run["name"] == "joint":
            calibrate_jointly(measurement_path, [grid_results[name] for name in needed], run["spec"], output, code_hash)
        else:
            calibrate_with_mcmc(measurement_path, grid_results[run["name"]], run["spec"], output, code_hash)


def calibrate_with_mcmc(measurement_path: str, grid_result_path: str, spec: dict, output: str, code_hash: str) -> None:
    """Write the MCMC posterior (ArviZ InferenceData) of one parameter for one measurement."""
    import numpy as np

    from . import mcmc_calibration, provenance
    from . import sampling as mcmc

    measurement, data, sigma, values, grid, prior = _calibration_inputs(measurement_path, spec)
    grid_posterior = _grid_posterior(grid_result_path, prior)
    start = time.perf_counter()
    idata = mcmc_calibration.calibrate_mcmc(
        data, sigma, grid, prior, grid_posterior, values, measurement.sampling, spec["channels"],
        mcmc.MCMCSettings.from_config(spec["mcmc"]), spec["max_step"],
        attrs={"settings": json.dumps(spec, sort_keys=True), **provenance.attributes(code_hash)},
        proposal=spec["mcmc"].get("proposal", "move"),
    )
    row = mcmc_calibration.mcmc_summary(idata, grid.parameter, prior, grid_posterior, sigma, spec["chi2_max"])
    log.info("MCMC of %s on %s in %.1f s: %s", grid.parameter, measurement.name, time.perf_counter() - start, row)
    idata.attrs.update({**_labels(measurement), "parameter": grid.parameter, "method": "mcmc",
                        **{k: int(v) if isinstance(v, (bool, np.bool_)) else v for k, v in row.items()}})
    mcmc.save(idata, output)


def calibrate_jointly(measurement_path: str, grid_result_paths: list[str], spec: dict, output: str, code_hash: str) -> None:
    """Write the joint posterior (ArviZ InferenceData; :func:`mcmc_calibration.calibrate_joint`) of several parameters,
    with the channels' noise σ known or inferred (``infer_sigma``), for one measurement; the summary rows
    (:func:`mcmc_calibration.joint_summary`, χ² against the file's σ when it has one) are the ``summary``
    attribute as JSON.  ``grid_result_paths`` are the parameters' grid calibrations, in the order of
    ``spec["parameters"]``."""
    from . import calibration, mcmc_calibration, provenance
    from . import sampling as mcmc

    infer_sigma = bool(spec.get("infer_sigma", False))
    measurement, data, sigma, values = _measurement_inputs(measurement_path, spec, need_sigma=not infer_sigma)
    names = list(spec["parameters"])
    if len(grid_result_paths) != len(names):
        raise ValueError(f"need one grid result per parameter ({', '.join(names)}), got {len(grid_result_paths)}")
    grids = [calibration.GridSpec.from_config(name, spec["parameters"][name]["grid"]) for name in names]
    priors = [calibration.NormalPrior(**spec["parameters"][name]["prior"]) for name in names]
    grid_posteriors = [_grid_posterior(path, prior, name) for path, prior, name in zip(grid_result_paths, priors, names)]
    start = time.perf_counter()
    idata = mcmc_calibration.calibrate_joint(
        data, None if infer_sigma else sigma, grids, priors, grid_posteriors, values, measurement.sampling,
        spec["channels"], mcmc.MCMCSettings.from_config(spec["mcmc"]), infer_sigma, spec["max_step"],
        attrs={"settings": json.dumps(spec, sort_keys=True), **provenance.attributes(code_hash)},
    )
    rows = mcmc_calibration.joint_summary(idata, dict(zip(names, priors)), spec["chi2_max"], sigma)
    log.info("joint posterior of %s on %s by %s in %.1f s: %s", idata.attrs["jointly"], measurement.name, idata.attrs["method"],
             time.perf_counter() - start, rows)
    idata.attrs.update({**_labels(measurement), "summary": json.dumps(rows)})
    mcmc.save(idata, output)


def _grid_posterior(path: str, prior, parameter: str | None = None):
    """The grid posterior of a ``calibrate-grid`` result under ``prior`` (of ``parameter``, when given)."""
    import xarray as xr

    from . import likelihood

    with xr.open_dataset(path, engine="netcdf4") as done:
        if parameter is not None and done.attrs.get("parameter") != parameter:
            raise ValueError(f"{path}: a grid calibration of {done.attrs.get('parameter')!r}, expected {parameter!r}")
        grid = done["grid"].values
        return likelihood.grid_posterior(grid, done["log_likelihood"].values, prior.log_pdf(grid))


def _calibration_inputs(measurement_path: str, spec: dict):
    """The measurement, its calibration channels and their σ, the healthy model at its condition, and
    the parameter's grid and prior."""
    from . import calibration

    measurement, data, sigma, values = _measurement_inputs(measurement_path, spec)
    grid = calibration.GridSpec.from_config(spec["parameter"], spec["grid"])
    prior = calibration.NormalPrior(**spec["prior"])
    return measurement, data, sigma, values, grid, prior


def _measurement_inputs(measurement_path: str, spec: dict, need_sigma: bool = True):
    """The measurement, its calibration channels and their σ (None if the file has none and it is not
    needed), and the healthy model at its condition."""
    from . import io, model

    # The study's own simulations, calibrated on the model's clock as the paper does.
    measurement = io.read_measurement(measurement_path, {k: spec["values"][k] for k in model.OPERATING_PARAMETERS}, None)
    missing = [c for c in spec["channels"] if c not in measurement.channels]
    if missing:
        raise io.MeasurementError(measurement_path, f"has no channel {missing[0]} to calibrate on")
    if measurement.sigma is None and need_sigma:
        raise io.MeasurementError(measurement_path, "no noise level (coordinate sigma) to calibrate with")
    rows = [measurement.channels.index(c) for c in spec["channels"]]
    values = {**spec["values"], **measurement.operating}
    sigma = None if measurement.sigma is None else measurement.sigma[rows]
    return measurement, measurement.y[rows], sigma, values


def _true_value(measurement, parameter: str) -> float:
    """The parameter's value in a simulated measurement (its ``parameters`` attribute), else NaN."""
    values = json.loads(measurement.attrs.get("parameters", "{}"))
    return float(values.get(parameter, "nan"))


def _labels(measurement) -> dict:
    labels = {key: measurement.attrs[key] for key in ("variant", "scenario", "snr_db", "seed") if key in measurement.attrs}
    return {"measurement": measurement.name, **labels}


def summarize(paths: list[str], output: str) -> None:
    """Write the study's summary table (CSV), one row per calibration file."""
    import xarray as xr

    from . import calibration, comparison, io
    from . import sampling as mcmc

    results = []
    for path in paths:
        if path.endswith("_mcmc.nc"):
            idata = mcmc.load(path)
            if "jointly" in idata.attrs:  # one row per sampled variable; the priors are truncated to `support`
                rows, support = json.loads(idata.attrs["summary"]), json.loads(idata.attrs["support"])
            else:  # the prior is truncated to the grid
                grid = json.loads(idata.attrs["settings"])["grid"]
                rows, support = [{}], {idata.attrs["parameter"]: (grid["low"], grid["high"])}
            for row in rows:
                name = row.get("parameter", idata.attrs.get("parameter"))
                grid, density = comparison.sample_density(idata.posterior[name].values.ravel(), tuple(support[name]))
                results.append({**idata.attrs, **row, "grid": grid, "posterior": density})
        else:
            with xr.open_dataset(path, engine="netcdf4") as ds:
                results.append({**ds.attrs, "grid": ds["grid"].values, "posterior": ds["posterior"].values})
    rows = calibration.summary_rows(results)
    io.write_csv(output, calibration.SUMMARY_COLUMNS, rows)
    log.info("summarized %d calibrations into %s", len(rows), output)


def compare(paths: list[str], output: str, code_hash: str) -> None:
    """Write the Hellinger distances between all scenarios' grid posteriors (the signature library's
    matrices) and each calibration's reduced χ², for one study variant."""
    import numpy as np
    import xarray as xr

    from . import comparison, io, provenance

    posteriors, chi2 = {}, {}
    for path in paths:
        with xr.open_dataset(path, engine="netcdf4") as ds:
            key = (ds.attrs["scenario"], ds.attrs["parameter"], float(ds.attrs["snr_db"]), int(ds.attrs["seed"]))
            posteriors[key] = (ds["grid"].values, ds["posterior"].values)
            chi2[key] = float(ds.attrs["chi2_red"])
    distances = comparison.signature_matrices(posteriors)
    chi2_red = xr.full_like(distances.isel(reference=0, drop=True), np.nan)
    for (scenario, parameter, snr, seed), value in chi2.items():
        chi2_red.loc[{"scenario": scenario, "parameter": parameter, "snr_db": snr, "seed": seed}] = value
    chi2_red.attrs.update(long_name="reduced chi-square of the best-fitting calibrated model", units="1")
    ds = xr.Dataset(
        {"hellinger": distances, "chi2_red": chi2_red},
        attrs={
            "title": "newdyn posterior signatures: Hellinger distances between scenarios' grid posteriors",
            "sources": json.dumps(sorted(paths)),
            **provenance.attributes(code_hash),
        },
    )
    io.write_netcdf(ds, output)
    log.info("compared %d posteriors into %s", len(posteriors), output)


def plot_figures(kind: str, figures: list[dict], code_hash: str) -> None:
    """Draw the figures of one stage of the study (each a PNG and a PDF) in one process, which imports matplotlib (and
    ArviZ) once for all of them: ``figures`` as :func:`plot` takes them, each its ``png``, ``inputs`` and the drawing's
    settings."""
    for figure in figures:
        plot(kind, code_hash=code_hash, **figure)
        log.info("drew %s into %s", kind, figure["png"])


def plot(kind: str, png: str, inputs: list[str], code_hash: str, measurement: str | None = None,
         chi2_png: str | None = None, snr_db: float | None = None, seed: int | None = None) -> None:
    """Draw one figure of the study (PNG and PDF) with :mod:`newdyn.plots`."""
    from . import plots

    if kind == "posteriors":
        plots.posterior_panels(inputs, png, code_hash=code_hash)
    elif kind == "overlays":
        plots.model_overlays(measurement, inputs, png, code_hash=code_hash)
    elif kind == "mcmc":
        plots.mcmc_diagnostics(inputs, png, code_hash=code_hash)
    elif kind == "signatures":
        plots.signature_heatmaps(inputs[0], png, snr_db, seed, code_hash=code_hash)
    elif kind == "summary":
        plots.summary_heatmaps(inputs[0], png, chi2_png, code_hash=code_hash)


def diagnose_measurement(measurement_path: str, grid_paths: list[str], bank_path: str | None, spec: dict, verdict: str, table: str,
                         netcdf: str, posterior: str, discovery: str, code_hash: str) -> None:
    """Diagnose one measurement file: verdict (JSON), model versions and posteriors (NetCDF), the effect's posterior,
    and a folder with the discovered term's effect file when nothing of the library explains it."""
    from . import calibration, diagnosis, io, model, study
    from .settings import Settings

    settings = Settings.from_config(spec)
    measurement = io.read_measurement(measurement_path, {k: spec["operating"][k] for k in model.OPERATING_PARAMETERS},
                                      _warm_up(spec))
    start = time.perf_counter()
    result = diagnosis.diagnose(measurement, settings, calibration.grid_files(grid_paths), bank_path=bank_path)
    v = result.verdict
    log.info("%s: %s %s (chi2 %.4g -> %.4g) in %.1f s", measurement_path, v["verdict"], v["effect"], v["chi2_before"],
             v["chi2_after"], time.perf_counter() - start)
    diagnosis.write(result, verdict, table, netcdf, posterior, discovery, study.canonical_json(spec), code_hash)


def diagnose_machine(name: str, measurement_paths: list[str], verdict_paths: list[str], spec: dict, output: str,
                     discovery: str, code_hash: str) -> None:
    """One verdict for a machine from its recordings, each diagnosed alone before (its verdict.json, in the same order),
    and the folder ``discovery`` with the effect file of the term found across them (empty where none was fitted)."""
    from . import io, machine, model, provenance, study
    from .discovery import effect_file
    from .settings import Settings

    if len(measurement_paths) != len(verdict_paths):
        raise SystemExit(f"newdyn diagnose-machine: {len(measurement_paths)} recordings but {len(verdict_paths)} verdicts")
    settings = Settings.from_config(spec)
    operating = {k: spec["operating"][k] for k in model.OPERATING_PARAMETERS}
    recordings = [machine.Diagnosed(io.read_measurement(m, operating, _warm_up(spec)), json.loads(Path(v).read_text()))
                  for m, v in zip(measurement_paths, verdict_paths)]
    start = time.perf_counter()
    found = machine.diagnose(name, recordings, settings)
    log.info("machine %s: %s in %.1f s", name, found.verdict["statement"], time.perf_counter() - start)
    effect_file.write(discovery, found.effect_file)
    io.write_json(output, {**found.verdict, "settings": json.loads(study.canonical_json(spec)), **provenance.attributes(code_hash)})


def write_bank(spec: dict, grid_paths: list[str], output: str, code_hash: str) -> None:
    """The study's bank (newdyn.bank) for a diagnosis spec at its operating condition, on the record a diagnosis
    compares (``spec["sampling"]`` from its warm-up, :func:`_warm_up`), on the study's coarse grids where they are
    that record's: every diagnosis at that condition reuses it."""
    from . import calibration, diagnosis, io, provenance, slots
    from .settings import Settings

    settings = Settings.from_config(spec)
    values = slots.complete({**spec["rig"], **spec["operating"]})
    study_record = _sampling(spec["sampling"])
    sampling = io.model_sampling(study_record.fs, study_record.n_samples, _warm_up(spec))
    paths = calibration.grid_files(grid_paths)
    coarse = {p: calibration.coarse_models(paths.get(p), grid, values, sampling, settings.channels, settings.max_step)
              for p, grid in settings.grids.items()}
    start = time.perf_counter()
    bank = diagnosis.study_bank(None, settings, {h.name: h for h in settings.hypotheses()}, values, sampling, coarse)
    log.info("%d signatures on %d grids and the members of %d hypotheses in %.1f s", bank.sizes["signature"], bank.sizes["parameter"],
             sum(name.startswith("members_") for name in bank.data_vars), time.perf_counter() - start)
    bank.attrs.update(provenance.attributes(code_hash))
    io.write_netcdf(bank, output)


def plot_diagnosis(verdict: str, netcdf: str, posterior: str, outputs: dict, code_hash: str) -> None:
    from . import plots

    plots.diagnosis_figures(verdict, netcdf, posterior, outputs, code_hash)


def verdict_page(verdict: str, output: str, code_hash: str) -> None:
    from . import io, provenance, verdicts

    text = verdicts.page(json.loads(Path(verdict).read_text()), provenance.attributes(code_hash))
    io.atomic_write(output, lambda tmp: Path(tmp).write_text(text))


def plot_machine(verdict: str, output: str, code_hash: str) -> None:
    from . import plots

    plots.machine_verdict(json.loads(Path(verdict).read_text()), output, code_hash, [verdict])


def draw_hidden(spec: dict, output: str, code_hash: str) -> None:
    """Draw a hidden set's cases and write their truth (the one file that holds it).  The spec holds
    the config's ``hidden`` section (its draw ranges and classes resolved by
    :func:`newdyn.study.hidden_ranges` and :func:`newdyn.study.hidden_classes`)."""
    from . import hidden, study

    cases = hidden.draw_cases(spec["hidden"], spec["set"], spec["values"], study.hidden_ranges(spec),
                              study.hidden_classes(spec), spec.get("sensors"), spec.get("channels", ()),
                              fs=_sampling(spec["sampling"]).fs)
    machines = spec["hidden"]["sets"][spec["set"]]
    if "recordings" in machines:
        cases = hidden.draw_recordings(cases, spec["set"], machines, spec["operating_range"], spec["channels"], spec["values"],
                                       _sampling(spec["sampling"]), spec["hidden"]["snr_db"], spec["max_step"])
    hidden.write_truth(cases, output, code_hash)
    log.info("drew %d hidden cases of set %s", len(cases), spec["set"])


def write_hidden_measurement(truth: str, name: str, spec: dict, output: str, code_hash: str) -> None:
    """Simulate one hidden case into a measurement file that holds nothing of its truth."""
    from . import hidden

    machine, _, recording = name.partition("/")  # a machine set's recording is <machine>/<recording>
    case = next(c for c in hidden.read_truth(truth) if c["name"] == machine)
    if recording:
        hidden.write_recording_measurement(case, recording, spec["values"], _sampling(spec["sampling"]),
                                           spec["hidden"]["snr_db"], output, code_hash, spec["max_step"])
    else:
        hidden.write_case_measurement(case, spec["values"], _sampling(spec["sampling"]), spec["hidden"]["snr_db"], output,
                                      code_hash, spec["max_step"])


def score_hidden(truth: str, verdict_paths: list[str], output: str, table: str, figure: str, chi2_max: float,
                 code_hash: str, recording_paths: list[str] = ()) -> None:
    """Reveal a hidden set: score every diagnosis against the truth (JSON, CSV and a figure); for a machine set, also
    each recording's own verdict (``recording_paths``, results/<set>/diagnosis/<machine>/<recording>/verdict.json)."""
    from . import hidden, plots

    cases = hidden.read_truth(truth)
    verdicts = {Path(path).parent.name: json.loads(Path(path).read_text()) for path in verdict_paths}
    result = hidden.score(cases, verdicts, chi2_max)
    if recording_paths:
        result["single_recordings"] = hidden.score_recordings(cases, {
            f"{Path(path).parent.parent.name}/{Path(path).parent.name}": json.loads(Path(path).read_text())
            for path in recording_paths})
    hidden.write_score(result, output, table, code_hash)
    name = Path(truth).parent.name
    plots.blind_test_figure(result, figure, f"hidden set {name}", code_hash, [truth, *verdict_paths])
    log.info("hidden set %s: top-1 accuracy %.3f", name, result["accuracy"])


def _warm_up(spec: dict) -> float:
    """How long the model runs from its steady state before it is compared with a recording: until the rig has
    forgotten what the linear steady state left out (:func:`newdyn.model.settling_time`)."""
    from . import model

    return model.settling_time({**spec["rig"], **spec["operating"]})


def _sampling(window: dict):
    from . import model

    # canonical JSON holds every number as a float
    return model.Sampling(fs=window["fs"], t_first=window["t_first"], n_samples=int(window["n_samples"]))


def _users_problem(error: Exception) -> str | None:
    """The one line of an error in what the user gave (a measurement, a config, an effect file, a path), else None:
    any other error is a bug in newdyn and keeps its traceback."""
    from . import config, effects, io

    if isinstance(error, (io.MeasurementError, config.ConfigError, effects.EffectError)):
        return str(error)
    if isinstance(error, OSError):
        return f"{error.filename}: {error.strerror}" if error.filename and error.strerror else str(error)
    return None


def _parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(prog="newdyn", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"newdyn {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("check", help="check measurement files by hand, as the workflow does before a diagnosis")
    p.add_argument("paths", nargs="+", metavar="path",
                   help="a measurement file (.nc or .csv), or a folder of them (measurements/, a machine's folder)")
    p.add_argument("--config", action="append", dest="configs", metavar="FILE",
                   help=f"the study's config (default {DEFAULT_CONFIG}); repeat it to merge files in order, as Snakemake "
                        f"merges them: snakemake --configfile my.yaml is --config {DEFAULT_CONFIG} --config my.yaml")
    p = commands.add_parser("check-config", help="check a study config as the workflow does, without running anything")
    p.add_argument("paths", nargs="*", default=[DEFAULT_CONFIG], metavar="file",
                   help=f"config files, merged in the order given as Snakemake merges them (default {DEFAULT_CONFIG})")

    def command(name, help, spec=None):
        """A subcommand with the --output and --code-hash every workflow job passes (and --spec if given)."""
        p = commands.add_parser(name, help=help)
        if spec:
            p.add_argument("--spec", required=True, help=f"{spec} as JSON (built by the workflow)")
        p.add_argument("--output", required=True)
        p.add_argument("--code-hash", default="", help="hash of the science code this job depends on (a change reruns the job)")
        return p

    command("simulate", "simulate one scenario into a clean measurement file", "scenario spec")
    p = command("add-noise", "add seeded white Gaussian noise at an SNR")
    p.add_argument("--input", required=True)
    p.add_argument("--snr-db", type=float, required=True)
    p.add_argument("--seed", type=int, required=True)
    command("grid-models", "simulate the coarse likelihood grid of a calibration parameter", "grid spec")
    p = commands.add_parser("calibrate-grid", help="grid posterior of each parameter for a measurement")
    p.add_argument("--spec", required=True, help="the parameters (each its parameter, prior and grid) and the "
                   "calibration settings as JSON (built by the workflow)")
    p.add_argument("--measurement", required=True)
    p.add_argument("--grids", required=True, nargs="+", help="each parameter's coarse grid (from grid-models), in the spec's order")
    p.add_argument("--outputs", required=True, nargs="+", help="each parameter's grid calibration, in the spec's order")
    p.add_argument("--code-hash", default="")
    p = commands.add_parser("calibrate-mcmc", help="MCMC posteriors of a measurement: of single parameters, and of "
                            "several at once (and optionally σ)")
    p.add_argument("--measurement", required=True)
    p.add_argument("--grid-results", required=True, nargs="+",
                   help="the parameters' grid calibrations, in any order (each says which parameter it holds; they start the walkers)")
    p.add_argument("--spec", required=True, help="the runs as JSON (built by the workflow): {effects, runs: [{name, spec}]}, "
                   "name a parameter or 'joint'")
    p.add_argument("--outputs", required=True, nargs="+", help="each run's posterior, in the spec's order")
    p.add_argument("--code-hash", default="")
    p = command("compare", "Hellinger distances between all scenarios' grid posteriors")
    p.add_argument("inputs", nargs="+", help="grid calibration files of one study variant")
    p = commands.add_parser("plot", help="draw figures of one kind (each a PNG, and a PDF beside it)")
    p.add_argument("kind", choices=["posteriors", "overlays", "mcmc", "signatures", "summary"])
    p.add_argument("--figures", required=True, help="the figures as JSON (built by the workflow), a list of objects: "
                   "png, the PNG to write; inputs, the grid calibrations (posteriors, overlays), a measurement's MCMC "
                   "results, the comparison file (signatures) or the summary table; measurement (overlays), the "
                   "measurement the grid calibrations fitted; snr_db and seed (signatures), which SNR and seed; "
                   "chi2_png (summary), the χ² heatmap (png gets the Hellinger one)")
    p.add_argument("--code-hash", default="")
    p = commands.add_parser("diagnose", help="diagnose a measurement: which hypothesis explains it")
    p.add_argument("--measurement", required=True)
    p.add_argument("--spec", required=True, help="the diagnosis settings as JSON (built by the workflow)")
    p.add_argument("--grids", nargs="*", default=[], help="the study's coarse grid files, in any order (each says which "
                   "parameter it holds; reused when their condition is the measurement's)")
    p.add_argument("--bank", help="the study's bank: signatures and members (reused when its condition is the measurement's)")
    for output in ("verdict", "table", "netcdf", "posterior", "discovery"):
        p.add_argument(f"--{output}", required=True)
    p.add_argument("--code-hash", default="")
    p = command("diagnose-machine", "one verdict for a machine from its recordings, each diagnosed alone first", "diagnosis spec")
    p.add_argument("--name", required=True, help="the machine's name (its folder in measurements/)")
    p.add_argument("--recordings", required=True, nargs="+", help="the machine's measurement files")
    p.add_argument("--verdicts", required=True, nargs="+", help="each recording's own verdict.json, in the same order")
    p.add_argument("--discovery", required=True, help="the folder for the effect file of a term found across the recordings")
    p = command("bank", "the signatures and members every diagnosis at one condition reuses", "diagnosis spec")
    p.add_argument("--grids", nargs="*", default=[], help="the study's coarse grid files, in any order")
    p = commands.add_parser("plot-diagnosis", help="the figures of one diagnosis")
    for name in ("verdict", "netcdf", "posterior", *DIAGNOSIS_FIGURES):
        p.add_argument(f"--{name.replace('_', '-')}", required=True)
    p.add_argument("--code-hash", default="")
    p = command("verdict-page", "a verdict's statement and findings as an HTML page for the report")
    p.add_argument("--verdict", required=True)
    p = commands.add_parser("plot-machine", help="the figure of a machine's verdict")
    p.add_argument("--verdict", required=True)
    p.add_argument("--output", required=True, help="the PNG (a PDF beside it)")
    p.add_argument("--code-hash", default="")
    command("hidden-draw", "draw a hidden set's cases and write their truth", "hidden-set spec")
    p = command("hidden-measurement", "simulate one hidden case into a measurement file without its truth", "hidden-set spec")
    p.add_argument("--truth", required=True)
    p.add_argument("--case", required=True)
    p = command("hidden-score", "score a hidden set's diagnoses against the truth")
    p.add_argument("--truth", required=True)
    p.add_argument("--table", required=True, help="one CSV row per case")
    p.add_argument("--figure", required=True, help="confusion matrix and parameter errors (PNG, PDF beside it)")
    p.add_argument("--chi2-max", type=float, required=True, help="a fit explains the data at this reduced χ² or less")
    p.add_argument("--effect", action="append", default=[], dest="effects",
                   help="one of the study's own effects (the config's effects; repeat for each), so that a verdict naming it is scored")
    p.add_argument("--recordings", nargs="*", default=[], help="a machine set's recordings' own verdict.json files, "
                   "scored beside the machines' verdicts")
    p.add_argument("verdicts", nargs="+", help="the set's verdict.json files (a machine set's: the machines')")
    p = command("summarize", "the summary table of all calibrations")
    p.add_argument("inputs", nargs="+", help="calibration files")

    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command (the stages' dispatch is read by :func:`newdyn.provenance.command_modules`); a bad file, config
    or path the user gave ends it with one line on stderr and status 1."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    logging.getLogger("arviz").setLevel(logging.WARNING)  # its optional subpackages' absence is no news to a user
    try:
        if args.command == "check":
            return check_measurements(args.paths, args.configs or [DEFAULT_CONFIG])
        if args.command == "check-config":
            check_config(args.paths)
            return 0
        # Every job works with the same effects: the built-ins and the study's own (files in effects/).
        from . import config

        config.use_effects(json.loads(args.spec) if getattr(args, "spec", None) else {"effects": getattr(args, "effects", [])})
        if args.command == "simulate":
            simulate_scenario(json.loads(args.spec), args.output, args.code_hash)
        elif args.command == "add-noise":
            add_noise_to_file(args.input, args.output, args.snr_db, args.seed, args.code_hash)
        elif args.command == "grid-models":
            simulate_grid_models(json.loads(args.spec), args.output, args.code_hash)
        elif args.command == "calibrate-grid":
            calibrate_on_grids(args.measurement, args.grids, json.loads(args.spec), args.outputs, args.code_hash)
        elif args.command == "calibrate-mcmc":
            calibrate_by_mcmc(args.measurement, args.grid_results, json.loads(args.spec)["runs"], args.outputs, args.code_hash)
        elif args.command == "compare":
            compare(args.inputs, args.output, args.code_hash)
        elif args.command == "plot":
            plot_figures(args.kind, json.loads(args.figures), args.code_hash)
        elif args.command == "diagnose":
            diagnose_measurement(args.measurement, args.grids, args.bank, json.loads(args.spec), args.verdict, args.table, args.netcdf,
                                 args.posterior, args.discovery, args.code_hash)
        elif args.command == "diagnose-machine":
            diagnose_machine(args.name, args.recordings, args.verdicts, json.loads(args.spec), args.output, args.discovery,
                             args.code_hash)
        elif args.command == "bank":
            write_bank(json.loads(args.spec), args.grids, args.output, args.code_hash)
        elif args.command == "plot-diagnosis":
            plot_diagnosis(args.verdict, args.netcdf, args.posterior, {name: getattr(args, name) for name in DIAGNOSIS_FIGURES},
                           args.code_hash)
        elif args.command == "verdict-page":
            verdict_page(args.verdict, args.output, args.code_hash)
        elif args.command == "plot-machine":
            plot_machine(args.verdict, args.output, args.code_hash)
        elif args.command == "hidden-draw":
            draw_hidden(json.loads(args.spec), args.output, args.code_hash)
        elif args.command == "hidden-measurement":
            write_hidden_measurement(args.truth, args.case, json.loads(args.spec), args.output, args.code_hash)
        elif args.command == "hidden-score":
            score_hidden(args.truth, args.verdicts, args.output, args.table, args.figure, args.chi2_max, args.code_hash,
                         args.recordings)
        elif args.command == "summarize":
            summarize(args.inputs, args.output)
    except (ValueError, OSError) as error:
        problem = _users_problem(error)
        if problem is None:
            raise
        print(f"newdyn {args.command}: {problem}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
