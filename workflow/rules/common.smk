# Config checking and the helpers rules share. Runs at parse time, before any job starts.
import sys

import newdyn.config
import newdyn.provenance

CONFIG_SOURCE = ", ".join(map(str, workflow.overwrite_configfiles or ["config/config.yaml"]))

try:
    newdyn.config.check(config, CONFIG_SOURCE, workflow.source_path("../schemas/config.schema.yaml"))
except newdyn.config.ConfigError as error:
    sys.exit(f"newdyn: bad config: {error}")

SCENARIOS = newdyn.config.scenario_names(config)
SNRS = [f"{snr:g}" for snr in config["noise"]["snr_db"]]
SEEDS = [str(seed) for seed in config["noise"]["seeds"]]

# Rules pass these as params so that an edit of the science code reruns exactly its jobs.
SIMULATION_CODE = newdyn.provenance.source_hash("model", "faults", "kernels", "simulation", "io")
NOISE_CODE = newdyn.provenance.source_hash("noise", "io")


wildcard_constraints:
    scenario="|".join(SCENARIOS) or "[A-Za-z0-9_-]+",
    parameter="|".join(config["calibration"]["parameters"]),
    snr=r"-?\d+(\.\d+)?",
    seed=r"\d+",


def _sampling_spec():
    sampling = newdyn.config.sampling(config)
    return {"fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples}


def simulation_spec(wildcards):
    """Everything that determines one scenario's simulation, as canonical JSON."""
    return newdyn.config.canonical_json(
        {
            "scenario": wildcards.scenario,
            "definition": config["scenarios"][wildcards.scenario] or {},
            "values": newdyn.config.scenario_values(config, wildcards.scenario),
            "sampling": _sampling_spec(),
            "channels": config["simulation"]["channels"],
            "max_step": config["simulation"]["max_step"],
        }
    )


def simulation_targets():
    return expand("results/simulations/{scenario}/clean.nc", scenario=SCENARIOS) + expand(
        "results/simulations/{scenario}/snr{snr}_seed{seed}.nc",
        scenario=SCENARIOS,
        snr=SNRS,
        seed=SEEDS,
    )


CALIBRATION = config["calibration"]
PARAMETERS = list(CALIBRATION["parameters"])
CALIBRATION_CODE = newdyn.provenance.source_hash("model", "kernels", "simulation", "io", "likelihood", "calibration")
MCMC_CODE = newdyn.provenance.source_hash(
    "model", "kernels", "simulation", "io", "likelihood", "calibration", "sampling", "comparison"
)
SUMMARY_CODE = newdyn.provenance.source_hash("calibration", "comparison", "sampling")


def grid_models_spec(wildcards):
    """What the coarse grid of one parameter depends on: the healthy rig, sampling, grid, channels."""
    return newdyn.config.canonical_json(
        {
            "parameter": wildcards.parameter,
            "grid": CALIBRATION["parameters"][wildcards.parameter]["grid"],
            "values": newdyn.config.base_values(config),
            "sampling": _sampling_spec(),
            "channels": CALIBRATION["channels"],
            "max_step": config["simulation"]["max_step"],
        }
    )


def calibration_spec(wildcards, mcmc=False):
    """What one calibration depends on besides its input files (MCMC: also the MCMC settings)."""
    spec = CALIBRATION["parameters"][wildcards.parameter]
    return newdyn.config.canonical_json(
        {
            **({"mcmc": CALIBRATION["mcmc"]} if mcmc else {}),
            "parameter": wildcards.parameter,
            "prior": spec["prior"],
            "grid": spec["grid"],
            "values": newdyn.config.base_values(config),
            "channels": CALIBRATION["channels"],
            "refine_points": CALIBRATION["refine_points"],
            "chi2_max": CALIBRATION["chi2_max"],
            "max_step": config["simulation"]["max_step"],
        }
    )


def mcmc_spec(wildcards):
    return calibration_spec(wildcards, mcmc=True)


def calibration_targets():
    pattern = "results/calibration/{scenario}/{parameter}/snr{snr}_seed{seed}_{method}.nc"
    grid = expand(pattern, scenario=SCENARIOS, parameter=PARAMETERS, snr=SNRS, seed=SEEDS, method="grid")
    mcmc = expand(
        pattern,
        scenario=SCENARIOS,
        parameter=CALIBRATION["mcmc"]["parameters"],
        snr=SNRS,
        seed=SEEDS,
        method="mcmc",
    )
    return grid + mcmc
