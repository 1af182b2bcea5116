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
    from . import io, model, provenance, simulation

    window = spec["sampling"]  # canonical JSON holds every number as a float
    sampling = model.Sampling(fs=window["fs"], t_first=window["t_first"], n_samples=int(window["n_samples"]))
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
        "code_hash": code_hash,
        "newdyn_version": provenance.versions()["newdyn"],
        "versions": provenance.versions(),
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
        noise_code_hash=code_hash,
        newdyn_version=provenance.versions()["newdyn"],
        versions=json.dumps(provenance.versions(), sort_keys=True),
    )
    io.write_netcdf(ds, output)
    log.info("added noise at %g dB (seed %d): sigma %s", snr_db, seed, {c: float(f"{s:.4g}") for c, s in zip(channels, sigma)})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="newdyn", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    p = commands.add_parser("simulate", help="simulate one scenario into a clean measurement file")
    p.add_argument("--spec", required=True, help="scenario spec as JSON (built by the workflow)")
    p.add_argument("--output", required=True)
    p.add_argument("--code-hash", default="")

    p = commands.add_parser("add-noise", help="add seeded white Gaussian noise at an SNR")
    p.add_argument("--input", required=True)
    p.add_argument("--output", required=True)
    p.add_argument("--snr-db", type=float, required=True)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--code-hash", default="")

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    if args.command == "simulate":
        simulate_scenario(json.loads(args.spec), args.output, args.code_hash)
    elif args.command == "add-noise":
        add_noise_to_file(args.input, args.output, args.snr_db, args.seed, args.code_hash)
    return 0


if __name__ == "__main__":
    sys.exit(main())
