"""``newdyn`` command line: one subcommand per workflow stage, each a thin call into the package.

Snakemake rules run these as shell commands so every job is its own process (its thread count
honoured, runnable on a cluster through Snakemake's executor plugins).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

log = logging.getLogger("newdyn")


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


def calibrate_on_grid(measurement_path: str, grid_path: str, spec: dict, output: str, code_hash: str) -> None:
    """Write the grid posterior of one parameter for one measurement, with its summary as attributes."""
    import numpy as np
    import xarray as xr

    from . import calibration, io, model, provenance

    channels = spec["channels"]
    measurement, data, sigma, values, grid, prior = _calibration_inputs(measurement_path, spec)

    with xr.open_dataset(grid_path, engine="netcdf4") as coarse:
        coarse.load()
    same_condition = (
        np.array_equal(coarse["time"].values, measurement.sampling.times)
        and all(float(coarse.attrs[k]) == values[k] for k in model.OPERATING_PARAMETERS)
        and np.array_equal(coarse["grid"].values, grid.axis)
    )
    if same_condition:
        coarse_models = coarse["model"].sel(channel=channels).values
    else:  # a measurement at another operating condition or sampling needs its own coarse grid
        log.info("measurement differs from the shared grid's condition: simulating its own coarse grid")
        coarse_models = calibration.simulate_grid(values, grid.parameter, grid.axis, measurement.sampling, channels, spec["max_step"])

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
            "method": "grid",
            **summary,
            "settings": json.dumps(spec, sort_keys=True),
            **provenance.attributes(code_hash),
        },
    )
    io.write_netcdf(ds, output)


def calibrate_with_mcmc(measurement_path: str, grid_result_path: str, spec: dict, output: str, code_hash: str) -> None:
    """Write the MCMC posterior (ArviZ InferenceData) of one parameter for one measurement."""
    import numpy as np
    import xarray as xr

    from . import calibration, likelihood, provenance
    from . import sampling as mcmc

    measurement, data, sigma, values, grid, prior = _calibration_inputs(measurement_path, spec)
    with xr.open_dataset(grid_result_path, engine="netcdf4") as done:
        grid_posterior = likelihood.grid_posterior(done["grid"].values, done["log_likelihood"].values, prior.log_pdf(done["grid"].values))
    m = spec["mcmc"]
    settings = mcmc.MCMCSettings(
        n_walkers=int(m["walkers"]), n_steps=int(m["steps"]), n_burn=int(m["burn"]), seed=int(m["seed"]),
        rhat_max=m["rhat_max"], ess_min=m["ess_min"], move=m["move"],
    )
    start = time.perf_counter()
    idata = calibration.calibrate_mcmc(
        data, sigma, grid, prior, grid_posterior, values, measurement.sampling, spec["channels"], settings, spec["max_step"],
        attrs={"settings": json.dumps(spec, sort_keys=True), **provenance.attributes(code_hash)},
    )
    row = calibration.mcmc_summary(idata, grid.parameter, prior, grid_posterior, sigma, spec["chi2_max"])
    log.info("MCMC of %s on %s in %.1f s: %s", grid.parameter, measurement.name, time.perf_counter() - start, row)
    idata.attrs.update({**_labels(measurement), "parameter": grid.parameter, "method": "mcmc",
                        **{k: int(v) if isinstance(v, (bool, np.bool_)) else v for k, v in row.items()}})
    mcmc.save(idata, output)


def _calibration_inputs(measurement_path: str, spec: dict):
    """The measurement, its calibration channels and their σ, the healthy model at its condition, and
    the parameter's grid and prior."""
    from . import calibration, io, model

    measurement = io.read_measurement(measurement_path, {k: spec["values"][k] for k in model.OPERATING_PARAMETERS})
    missing = [c for c in spec["channels"] if c not in measurement.channels]
    if missing:
        raise io.MeasurementError(measurement_path, f"has no channel {missing[0]} to calibrate on")
    if measurement.sigma is None:
        raise io.MeasurementError(measurement_path, "no noise level (coordinate sigma) to calibrate with")
    rows = [measurement.channels.index(c) for c in spec["channels"]]
    values = {**spec["values"], **measurement.operating}
    grid = calibration.GridSpec.from_config(spec["parameter"], spec["grid"])
    prior = calibration.NormalPrior(**spec["prior"])
    return measurement, measurement.y[rows], measurement.sigma[rows], values, grid, prior


def _labels(measurement) -> dict:
    labels = {key: measurement.attrs[key] for key in ("scenario", "snr_db", "seed") if key in measurement.attrs}
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
            draws = idata.posterior[idata.attrs["parameter"]].values.ravel()
            support = json.loads(idata.attrs["settings"])["grid"]  # the prior is truncated to the grid
            grid, density = comparison.sample_density(draws, (support["low"], support["high"]))
            results.append({**idata.attrs, "grid": grid, "posterior": density})
        else:
            with xr.open_dataset(path, engine="netcdf4") as ds:
                results.append({**ds.attrs, "grid": ds["grid"].values, "posterior": ds["posterior"].values})
    rows = calibration.summary_rows(results)
    io.atomic_write(output, lambda tmp: _write_csv(tmp, calibration.SUMMARY_COLUMNS, rows))
    log.info("summarized %d calibrations into %s", len(rows), output)


def _write_csv(path, columns, rows):
    import csv

    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def _sampling(window: dict):
    from . import model

    # canonical JSON holds every number as a float
    return model.Sampling(fs=window["fs"], t_first=window["t_first"], n_samples=int(window["n_samples"]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="newdyn", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

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
    p = command("calibrate-grid", "grid posterior of a parameter for a measurement", "calibration spec")
    p.add_argument("--measurement", required=True)
    p.add_argument("--grid", required=True, help="the parameter's coarse grid (from grid-models)")
    p = command("calibrate-mcmc", "MCMC posterior of a parameter for a measurement", "calibration spec")
    p.add_argument("--measurement", required=True)
    p.add_argument("--grid-result", required=True, help="the same calibration on the grid (starts the walkers)")
    p = command("summarize", "the summary table of all calibrations")
    p.add_argument("inputs", nargs="+", help="calibration files")

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    if args.command == "simulate":
        simulate_scenario(json.loads(args.spec), args.output, args.code_hash)
    elif args.command == "add-noise":
        add_noise_to_file(args.input, args.output, args.snr_db, args.seed, args.code_hash)
    elif args.command == "grid-models":
        simulate_grid_models(json.loads(args.spec), args.output, args.code_hash)
    elif args.command == "calibrate-grid":
        calibrate_on_grid(args.measurement, args.grid, json.loads(args.spec), args.output, args.code_hash)
    elif args.command == "calibrate-mcmc":
        calibrate_with_mcmc(args.measurement, args.grid_result, json.loads(args.spec), args.output, args.code_hash)
    elif args.command == "summarize":
        summarize(args.inputs, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
