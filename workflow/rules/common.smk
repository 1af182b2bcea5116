# Config checking and the helpers rules share. Runs at parse time, before any job starts.
import sys
from pathlib import Path

import newdyn.catalog
import newdyn.config
import newdyn.effects
import newdyn.provenance
from newdyn.cli import DIAGNOSIS_FIGURES

CONFIG_SOURCE = ", ".join(map(str, workflow.overwrite_configfiles or ["config/config.yaml"]))

try:
    newdyn.config.check(config, CONFIG_SOURCE, workflow.source_path("../schemas/config.schema.yaml"))
except newdyn.config.ConfigError as error:
    sys.exit(f"newdyn: bad config: {error}")

# Every variant is a whole study of its own (other rig values, channels, subsets) under results/<variant>/.
VARIANTS = {name: newdyn.config.variant_config(config, name) for name in newdyn.config.variant_names(config)}
SEEDS = [str(seed) for seed in config["noise"]["seeds"]]

# Rules pass the hash of the code their `newdyn` command runs as a param (code_hash), so that an edit of any
# module it imports, directly or through others, reruns exactly its jobs; an effect's own file counts only
# for the jobs that load it (effect_files).
EFFECTS = list(config.get("effects", []))  # the study's own effects, beside the built-ins


def effect_files(kinds=None):
    """The files of effects ``kinds`` (default: every active one)."""
    active = newdyn.effects.active()
    return [active[kind].source for kind in (active if kinds is None else kinds)]


def code_hash(command, files=()):
    """The hash of what ``newdyn <command>`` runs, with the effect ``files`` it loads (newdyn.provenance.command_hash)."""
    return newdyn.provenance.command_hash(command, files)


# On a cluster each job asks for its rule's memory [MB] and time [min]: a default study's measured peak
# (results/benchmarks/, python bench/bench_resources.py) with room for slower nodes and a first kernel compile.
# The light rules (noise, comparison, summary, figures, a hidden set's draw and score) are local rules: they run
# where Snakemake runs, as a cluster job's start (its own Snakemake parse) would cost more than they do.
def per_attempt(amount):
    """``amount`` of a resource, doubled on each retry (--retries): a job killed for memory or time gets more."""
    return lambda wildcards, attempt: amount * 2 ** (attempt - 1)


def simulation_code(wildcards):
    """The simulator's hash, with the file of the scenario's effect if it has one."""
    fault = (study(wildcards)["scenarios"][wildcards.scenario] or {}).get("fault") or {}
    kinds = [fault["kind"]] if fault.get("kind") in newdyn.effects.active() else []
    return code_hash("simulate", effect_files(kinds))


def _names(key):
    return sorted({name for study in VARIANTS.values() for name in key(study)})


wildcard_constraints:
    variant="|".join(VARIANTS),
    scenario="|".join(_names(lambda study: study["scenarios"])) or "[A-Za-z0-9_-]+",
    parameter="|".join(_names(lambda study: study["calibration"]["parameters"])),
    snr=r"-?\d+(\.\d+)?",
    seed=r"\d+",


def study(wildcards):
    """The config of the wildcards' variant."""
    return VARIANTS[wildcards.variant]


def _snrs(study):
    return [f"{snr:g}" for snr in study["noise"]["snr_db"]]


def _sampling_spec(study):
    sampling = newdyn.config.sampling(study)
    return {"fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples}


def simulation_spec(wildcards):
    """Everything that determines one scenario's simulation, as canonical JSON."""
    cfg = study(wildcards)
    return newdyn.config.canonical_json(
        {
            "scenario": wildcards.scenario,
            "variant": wildcards.variant,
            "definition": cfg["scenarios"][wildcards.scenario] or {},
            "values": newdyn.config.scenario_values(cfg, wildcards.scenario),
            "sampling": _sampling_spec(cfg),
            "channels": cfg["simulation"]["channels"],
            "max_step": cfg["simulation"]["max_step"],
            "effects": EFFECTS,
        }
    )


def measurement_targets(variant, clean=False):
    cfg = VARIANTS[variant]
    pattern = "results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc"
    noisy = expand(pattern, variant=variant, scenario=list(cfg["scenarios"]), snr=_snrs(cfg), seed=SEEDS)
    if not clean:
        return noisy
    return (
        expand("results/{variant}/simulations/{scenario}/clean.nc", variant=variant, scenario=list(cfg["scenarios"]))
        + noisy
    )


def simulation_targets():
    return [path for variant in VARIANTS for path in measurement_targets(variant, clean=True)]


def grid_models_spec(wildcards):
    """What the coarse grid of one parameter depends on: the healthy rig, sampling, grid, channels."""
    cfg = study(wildcards)
    calibration = cfg["calibration"]
    return newdyn.config.canonical_json(
        {
            "parameter": wildcards.parameter,
            "grid": calibration["parameters"][wildcards.parameter]["grid"],
            "values": newdyn.config.base_values(cfg),
            "sampling": _sampling_spec(cfg),
            "channels": calibration["channels"],
            "max_step": cfg["simulation"]["max_step"],
            "effects": EFFECTS,
        }
    )


def _calibration_settings(cfg):
    """What every calibration of a variant depends on besides its parameters and input files."""
    calibration = cfg["calibration"]
    return {
        "values": newdyn.config.base_values(cfg),
        "channels": calibration["channels"],
        "refine_points": calibration["refine_points"],
        "chi2_max": calibration["chi2_max"],
        "max_step": cfg["simulation"]["max_step"],
        "effects": EFFECTS,
    }


def calibration_spec(wildcards, mcmc=False):
    """What one calibration depends on besides its input files (MCMC: also the MCMC settings)."""
    cfg = study(wildcards)
    spec = cfg["calibration"]["parameters"][wildcards.parameter]
    return newdyn.config.canonical_json(
        {
            **({"mcmc": cfg["calibration"]["mcmc"]} if mcmc else {}),
            "parameter": wildcards.parameter,
            "prior": spec["prior"],
            "grid": spec["grid"],
            **_calibration_settings(cfg),
        }
    )


def mcmc_spec(wildcards):
    return calibration_spec(wildcards, mcmc=True)


def joint_spec(wildcards):
    """What the joint calibration of a measurement depends on besides its input files."""
    calibration = study(wildcards)["calibration"]
    joint = calibration["joint"]
    return newdyn.config.canonical_json(
        {
            "parameters": {name: calibration["parameters"][name] for name in joint["parameters"]},
            "infer_sigma": joint["infer_sigma"],
            "mcmc": {**calibration["mcmc"], "walkers": joint["walkers"], "steps": joint["steps"]},
            **_calibration_settings(study(wildcards)),
        }
    )


def mcmc_runs(cfg):
    """The MCMC calibrations of each measurement: one per MCMC parameter, and "joint" if configured."""
    calibration = cfg["calibration"]
    return calibration["mcmc"]["parameters"] + (["joint"] if calibration["joint"]["parameters"] else [])


def calibration_targets(variant, methods=("grid", "mcmc")):
    """A variant's calibration files."""
    cfg = VARIANTS[variant]
    pattern = "results/{variant}/calibration/{scenario}/{parameter}/snr{snr}_seed{seed}_{method}.nc"
    parameters = {"grid": list(cfg["calibration"]["parameters"]), "mcmc": mcmc_runs(cfg)}
    return [
        path
        for method in methods
        for path in expand(
            pattern,
            variant=variant,
            scenario=list(cfg["scenarios"]),
            parameter=parameters[method],
            snr=_snrs(cfg),
            seed=SEEDS,
            method=method,
        )
    ]


def all_calibration_targets():
    return [path for variant in VARIANTS for path in calibration_targets(variant)]


# --- figures
PAPER_FIGURES = {"fig3": ("kT1_up", ["kT1"]), "fig4": ("stick_slip", ["kT1", "kT3"])}


def _figure(stem, caption, category, **labels):
    """A figure's PNG (in the report, captioned) and its PDF."""
    png = report(
        f"{stem}.png", caption=f"../report/{caption}.rst", category=category, subcategory="{variant}", labels=labels
    )
    return {"png": png, "pdf": f"{stem}.pdf"}


def _grid_results(wildcards, parameters=None):
    cfg = study(wildcards)
    return expand(
        "results/{{variant}}/calibration/{{scenario}}/{parameter}/snr{{snr}}_seed{{seed}}_grid.nc",
        parameter=parameters or list(cfg["calibration"]["parameters"]),
    )


def figure_targets():
    targets = ["results/figures/summary_hellinger.png", "results/figures/summary_chi2.png"]
    for variant, cfg in VARIANTS.items():
        scenarios, parameters = cfg["scenarios"], cfg["calibration"]["parameters"]
        common = dict(variant=variant, snr=_snrs(cfg), seed=SEEDS)
        targets += expand("results/{variant}/figures/signatures_snr{snr}_seed{seed}.png", **common)
        for kind in ("posteriors", "overlays"):
            targets += expand(
                f"results/{{variant}}/figures/{kind}/{{scenario}}_snr{{snr}}_seed{{seed}}.png",
                scenario=list(scenarios),
                **common,
            )
        if mcmc_runs(cfg):
            targets += expand(
                "results/{variant}/figures/mcmc/{scenario}_snr{snr}_seed{seed}.png", scenario=list(scenarios), **common
            )
        for figure, (scenario, needed) in PAPER_FIGURES.items():
            if scenario in scenarios and all(p in parameters for p in needed):
                targets += expand("results/{variant}/figures/{figure}_snr{snr}_seed{seed}.png", figure=figure, **common)
    return targets


# --- diagnosis of measurements: users' files in measurements/, and hidden-effect sets drawn from a seed
HIDDEN_SETS = config["hidden"]["sets"]


# name -> file of every good measurement in measurements/; each bad one gets its one line on stderr and is
# left out, so it never stops the diagnosis of the good ones (the checks are remembered per file).
MEASUREMENTS, _bad = newdyn.catalog.good_measurements(
    "measurements",
    config["operating"],
    config["diagnosis"]["channels"],
    config["diagnosis"]["noise_band_hz"],
    ".snakemake/newdyn/measurements.json",
)
for _line in _bad:
    print(f"newdyn: skipping bad measurement: {_line}", file=sys.stderr)


def diagnosis_root(root, name):
    return f"{root}/diagnosis/{name}"


def measurement_file(wildcards):
    """A diagnosis's input file: the user's file, or a hidden set's drawn measurement."""
    if wildcards.root == "results":
        if wildcards.name not in MEASUREMENTS:
            raise ValueError(f"no good measurement measurements/{wildcards.name}.nc or .csv (see the lines above)")
        return MEASUREMENTS[wildcards.name]
    return f"{wildcards.root}/measurements/{wildcards.name}.nc"


def study_grids(wildcards):
    """The default study's coarse grids: the diagnosis reuses them when the measurement's condition is theirs."""
    if "default" not in VARIANTS:
        return []
    return expand(
        "results/default/calibration/grids/{parameter}.nc", parameter=list(config["calibration"]["parameters"])
    )


def diagnosis_spec(wildcards):
    return newdyn.config.canonical_json(
        {
            "rig": config["rig"],
            "operating": config["operating"],
            "sampling": _sampling_spec(config),
            "diagnosis": config["diagnosis"],
            "calibration": {
                key: config["calibration"][key] for key in ("parameters", "chi2_max", "refine_points", "mcmc")
            },
            "simulation": {"max_step": config["simulation"]["max_step"]},
            "effects": EFFECTS,
        }
    )


def hidden_cases(set_name):
    return [f"{set_name}_{i:02d}" for i in range(1, HIDDEN_SETS[set_name]["cases"] + 1)]


def diagnosis_targets(root, names):
    return expand("{root}/diagnosis/{name}/verdict.json", root=root, name=names) + expand(
        "{root}/diagnosis/{name}/figures/{figure}.png", root=root, name=names, figure=DIAGNOSIS_FIGURES
    )


def hidden_spec(wildcards):
    """What draws and simulates a hidden set: its name, cases and seed (not the other sets'), the draw's
    ranges, the rig and the record; for a set seen through instruments, their datasheets and the compared
    channels."""
    instruments = HIDDEN_SETS[wildcards.set].get("instruments", False)
    return newdyn.config.canonical_json(
        {
            "set": wildcards.set,
            "hidden": {**config["hidden"], "sets": {wildcards.set: HIDDEN_SETS[wildcards.set]}},
            "values": newdyn.config.base_values(config),
            "sampling": _sampling_spec(config),
            "max_step": config["simulation"]["max_step"],
            "effects": EFFECTS,
            **(
                {
                    "sensors": config["diagnosis"]["sensors"],
                    "channels": config["diagnosis"]["channels"],
                }
                if instruments
                else {}
            ),
        }
    )


def hidden_targets(set_name):
    """A hidden set's diagnoses, their figures and its score, if the set is configured."""
    if set_name not in HIDDEN_SETS:
        return []
    root = f"results/{set_name}"
    return diagnosis_targets(root, hidden_cases(set_name)) + [f"{root}/score.json", f"{root}/blind_test.png"]
