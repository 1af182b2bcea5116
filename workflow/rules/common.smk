# Config checking and the helpers rules share. Runs at parse time, before any job starts.
import re
import sys
from pathlib import Path

import newdyn.catalog
import newdyn.measurement_files
import newdyn.config
import newdyn.study
import newdyn.effects
import newdyn.hidden_sets
import newdyn.provenance
import newdyn.verdicts
from newdyn.cli import DIAGNOSIS_FIGURES

# The files the config came from, in the order Snakemake merged them: config/config.yaml (when the working directory
# has one and --replace-workflow-config did not drop it), then each --configfile over it.
_BASE_REPLACED = workflow.config_settings.replace_workflow_config and bool(workflow.config_settings.overwrite_config)
CONFIG_SOURCE = ", ".join(
    [str(path) for path in workflow.configfiles if path not in workflow.overwrite_configfiles and not _BASE_REPLACED]
    + [str(path) for path in workflow.overwrite_configfiles]
)

try:
    newdyn.config.check(config, CONFIG_SOURCE, workflow.source_path("../schemas/config.schema.yaml"))
except newdyn.config.ConfigError as error:
    sys.exit(f"newdyn: bad config: {error}")

# Every variant is a whole study of its own (other rig values, channels, subsets) under results/<variant>/.
VARIANTS = {name: newdyn.study.variant_config(config, name) for name in newdyn.study.variant_names(config)}
SEEDS = [str(seed) for seed in config["noise"]["seeds"]]

# On a batch system a scenario is one job: its simulation, its noisy copies and their calibrations, the rules of this
# group (one group job per scenario; a local run ignores groups). Each job a batch system runs waits for its queue,
# its start and the next status check, which cost more than most of these jobs' work.
SCENARIO_GROUP = "scenario"
# The same for what every diagnosis reads (the study's coarse grids and its hypothesis bank: one job), and for a blind
# set's case (its measurement drawn and diagnosed: one job per case, as a bank shared by all would join them into one).
LIBRARY_GROUP = "library"
CASE_GROUP = "case"

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
    sampling = newdyn.study.sampling(study)
    return {"fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples}


def simulation_spec(wildcards):
    """Everything that determines one scenario's simulation, as canonical JSON."""
    cfg = study(wildcards)
    return newdyn.study.canonical_json(
        {
            "scenario": wildcards.scenario,
            "variant": wildcards.variant,
            "definition": cfg["scenarios"][wildcards.scenario] or {},
            "values": newdyn.study.scenario_values(cfg, wildcards.scenario),
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
    return newdyn.study.canonical_json(
        {
            "parameter": wildcards.parameter,
            "grid": calibration["parameters"][wildcards.parameter]["grid"],
            "values": newdyn.study.base_values(cfg),
            "sampling": _sampling_spec(cfg),
            "channels": newdyn.study.grid_channels(cfg),
            "max_step": cfg["simulation"]["max_step"],
            "effects": EFFECTS,
        }
    )


def _calibration_settings(cfg):
    """What every calibration of a variant depends on besides its parameters and input files."""
    calibration = cfg["calibration"]
    return {
        "values": newdyn.study.base_values(cfg),
        "channels": calibration["channels"],
        "refine_points": calibration["refine_points"],
        "chi2_max": calibration["chi2_max"],
        "max_step": cfg["simulation"]["max_step"],
        "effects": EFFECTS,
    }


def _grid_parameters(cfg):
    """The parameters the variant ``cfg`` calibrates on grids, by name (the config's order of keys changes nothing)."""
    return sorted(cfg["calibration"]["parameters"])


def grid_files(cfg):
    """The coarse grid of each parameter of the variant ``cfg``, a pattern of {variant}."""
    return expand("results/{{variant}}/calibration/grids/{parameter}.nc", parameter=_grid_parameters(cfg))


def _measurement_calibrations(parameters, method):
    """One measurement's calibration files of ``parameters`` (names, or "joint") by ``method`` (grid or mcmc), a
    pattern of {variant}, {scenario}, {snr} and {seed}."""
    return expand(
        "results/{{variant}}/calibration/{{scenario}}/{parameter}/snr{{snr}}_seed{{seed}}_{method}.nc",
        parameter=parameters,
        method=method,
    )


def grid_calibration_files(cfg):
    """The grid calibration of each parameter of the variant ``cfg`` on one measurement, in the order of
    grid_calibration_spec's parameters."""
    return _measurement_calibrations(_grid_parameters(cfg), "grid")


def grid_calibration_spec(wildcards):
    """What the grid calibrations of one measurement depend on besides its input files: each parameter's prior and
    grid (in the order of grid_calibration_files), and the calibration settings."""
    cfg = study(wildcards)
    return newdyn.study.canonical_json(
        {
            "parameters": [
                {"parameter": name, **{key: cfg["calibration"]["parameters"][name][key] for key in ("prior", "grid")}}
                for name in _grid_parameters(cfg)
            ],
            **_calibration_settings(cfg),
        }
    )


def mcmc_spec(wildcards):
    """What the MCMC calibrations of one measurement depend on besides its input files: per run of
    newdyn.study.mcmc_runs (in that order), a parameter's own or the joint one's settings."""
    cfg = study(wildcards)
    calibration = cfg["calibration"]
    joint = calibration["joint"]
    runs = []
    for run in newdyn.study.mcmc_runs(cfg):
        if run == "joint":
            spec = {
                "parameters": {name: calibration["parameters"][name] for name in joint["parameters"]},
                "infer_sigma": joint["infer_sigma"],
                # the joint runs take emcee's move (the grid proposal is one parameter's) and their own burn-in, if set
                "mcmc": {
                    **{key: value for key, value in calibration["mcmc"].items() if key != "proposal"},
                    "walkers": joint["walkers"],
                    "steps": joint["steps"],
                    "burn": joint.get("burn", calibration["mcmc"]["burn"]),
                },
            }
        else:
            spec = {
                "mcmc": calibration["mcmc"],
                "parameter": run,
                "prior": calibration["parameters"][run]["prior"],
                "grid": calibration["parameters"][run]["grid"],
            }
        runs.append({"name": run, "spec": {**spec, **_calibration_settings(cfg)}})
    # the effects at the top too: the job loads them (newdyn.cli.main) before it reads the runs
    return newdyn.study.canonical_json({"effects": EFFECTS, "runs": runs})


def mcmc_calibration_files(cfg):
    """The MCMC calibrations of the variant ``cfg`` on one measurement, in the order of newdyn.study.mcmc_runs."""
    return _measurement_calibrations(newdyn.study.mcmc_runs(cfg), "mcmc")


def mcmc_grid_results(cfg):
    """The grid calibrations that start the MCMC calibrations of the variant ``cfg`` on one measurement."""
    calibration = cfg["calibration"]
    parameters = dict.fromkeys(calibration["mcmc"]["parameters"] + calibration["joint"]["parameters"])
    return _measurement_calibrations(list(parameters), "grid")


def calibration_targets(variant, methods=("grid", "mcmc")):
    """A variant's calibration files."""
    cfg = VARIANTS[variant]
    pattern = "results/{variant}/calibration/{scenario}/{parameter}/snr{snr}_seed{seed}_{method}.nc"
    parameters = {"grid": list(cfg["calibration"]["parameters"]), "mcmc": newdyn.study.mcmc_runs(cfg)}
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


# --- figures: one job per stage draws every figure of that stage (figures.smk), each with its own inputs
# The report's categories in the order a reader meets them; each result names its category, the number is derived.
REPORT_CATEGORIES = [
    "Summary",
    "The paper's figures",
    "Calibration",
    "Model vs data",
    "MCMC diagnostics",
    "Comparison",
    "Diagnosis",
    "Blind test",
]


def category(name):
    """A report category's title, numbered by its place in REPORT_CATEGORIES."""
    return f"{REPORT_CATEGORIES.index(name)} {name}"


PAPER_FIGURES = {"fig3": ("kT1_up", ["kT1"]), "fig4": ("stick_slip", ["kT1", "kT3"])}


def _figure(stem, caption, report_category, subcategory=None, labels=None, inputs=(), **drawing):
    """A figure: its PNG (in the report, captioned) and PDF, the files it is drawn from and what else its drawing
    takes (newdyn plot's --figures)."""
    png = report(
        f"{stem}.png",
        caption=f"../report/{caption}.rst",
        category=report_category,
        subcategory=subcategory,
        labels=labels,
    )
    return {"png": png, "pdf": f"{stem}.pdf", "inputs": list(inputs), **drawing}


def _measurement_figures(variant, cfg, scenario, snr, seed):
    """The figures of one measurement: its posteriors, its best fits against it and, with MCMC runs, their diagnostics."""
    measurement = f"results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc"
    results = f"results/{variant}/calibration/{scenario}/{{parameter}}/snr{snr}_seed{seed}_{{method}}.nc"
    grid = expand(results, parameter=list(cfg["calibration"]["parameters"]), method="grid")
    stem = f"results/{variant}/figures/{{kind}}/{scenario}_snr{snr}_seed{seed}"
    labels = {"scenario": scenario, "snr_dB": snr, "seed": seed}
    figures = {
        "posteriors": [
            _figure(stem.format(kind="posteriors"), "posteriors", category("Calibration"), variant, labels, grid)
        ],
        "overlays": [
            _figure(
                stem.format(kind="overlays"),
                "overlays",
                category("Model vs data"),
                variant,
                labels,
                grid,
                measurement=measurement,
            )
        ],
    }
    mcmc_runs = newdyn.study.mcmc_runs(cfg)
    if mcmc_runs:
        runs = expand(results, parameter=mcmc_runs, method="mcmc")
        figures["mcmc"] = [
            _figure(stem.format(kind="mcmc"), "mcmc", category("MCMC diagnostics"), variant, labels, runs)
        ]
    return figures


def _variant_figures(variant, cfg):
    """stage -> the figures of one variant."""
    stages = {"posteriors": [], "overlays": [], "mcmc": [], "signatures": []}
    for scenario in cfg["scenarios"]:
        for snr in _snrs(cfg):
            for seed in SEEDS:
                for stage, figures in _measurement_figures(variant, cfg, scenario, snr, seed).items():
                    stages[stage] += figures
    for snr in _snrs(cfg):
        for seed in SEEDS:
            for figure, (scenario, parameters) in PAPER_FIGURES.items():
                if scenario in cfg["scenarios"] and all(p in cfg["calibration"]["parameters"] for p in parameters):
                    grid = expand(
                        f"results/{variant}/calibration/{scenario}/{{parameter}}/snr{snr}_seed{seed}_grid.nc",
                        parameter=parameters,
                    )
                    stages["posteriors"].append(
                        _figure(
                            f"results/{variant}/figures/{figure}_snr{snr}_seed{seed}",
                            f"paper_{figure}",
                            category("The paper's figures"),
                            variant,
                            {"figure": figure, "snr_dB": snr, "seed": seed},
                            grid,
                        )
                    )
            stages["signatures"].append(
                _figure(
                    f"results/{variant}/figures/signatures_snr{snr}_seed{seed}",
                    "signatures",
                    category("Comparison"),
                    variant,
                    {"snr_dB": snr, "seed": seed},
                    [f"results/{variant}/comparison/hellinger.nc"],
                    snr_db=float(snr),
                    seed=int(seed),
                )
            )
    return stages


def _study_figures():
    """stage -> every figure of the study that its job draws, by file name (the config's order of keys changes nothing)."""
    stages = {"posteriors": [], "overlays": [], "mcmc": [], "signatures": []}
    for variant, cfg in VARIANTS.items():
        for stage, figures in _variant_figures(variant, cfg).items():
            stages[stage] += figures
    summary = _figure(
        "results/figures/summary_hellinger", "summary", category("Summary"), inputs=["results/summary.csv"]
    )
    chi2 = report("results/figures/summary_chi2.png", caption="../report/summary.rst", category=category("Summary"))
    stages["summary"] = [{**summary, "chi2_png": chi2, "chi2_pdf": "results/figures/summary_chi2.pdf"}]
    return {stage: sorted(figures, key=lambda figure: figure["png"]) for stage, figures in stages.items()}


STUDY_FIGURES = _study_figures()


def figure_inputs(stage):
    """Every file the figures of ``stage`` are drawn from."""
    return sorted(
        {path for figure in STUDY_FIGURES[stage] for path in [*figure["inputs"], figure.get("measurement")] if path}
    )


def figure_files(stage):
    """The PNG (marked for the report) and PDF of every figure of ``stage``."""
    return [
        figure[key]
        for figure in STUDY_FIGURES[stage]
        for key in ("png", "pdf", "chi2_png", "chi2_pdf")
        if key in figure
    ]


def figure_plan(stage):
    """The figures of ``stage`` as ``newdyn plot --figures`` takes them: each its PNG, input files and drawing's settings."""
    return newdyn.study.canonical_json(
        [
            {key: value for key, value in figure.items() if key not in ("pdf", "chi2_pdf")}
            for figure in STUDY_FIGURES[stage]
        ]
    )


def figure_targets():
    """Every figure's PNG, as a plain path: the report marks belong to the rules that draw them."""
    return [
        str(figure[key])
        for figures in STUDY_FIGURES.values()
        for figure in figures
        for key in ("png", "chi2_png")
        if key in figure
    ]


# --- diagnosis of measurements: users' files in measurements/, and hidden-effect sets drawn from a seed
HIDDEN_SETS = config["hidden"]["sets"]
STUDY_HIDDEN_SET = "demo"  # the hidden set the default target diagnoses beside the study


def diagnosis_threads(wildcards):
    """Two threads for a diagnosis (its hypotheses' fits side by side), one for the study's own hidden set's: beside
    the study's one-thread jobs a two-thread job waits until both cores are free, which is the study's end."""
    return 1 if wildcards.root == f"results/{STUDY_HIDDEN_SET}" else 2


# name -> file of every good measurement in measurements/; each bad one gets its one line on stderr and is
# left out, so it never stops the diagnosis of the good ones (the checks are remembered per file).
MEASUREMENTS, _bad = newdyn.catalog.good_measurements(
    "measurements",
    config["operating"],
    config["diagnosis"]["channels"],
    config["diagnosis"]["noise_band_hz"],
    ".snakemake/newdyn/measurements.json",
    config["rig"],
)
for _line in _bad:
    print(f"newdyn: skipping bad measurement: {_line}", file=sys.stderr)
# machine -> the names of its recordings (measurements/<machine>/<recording>.nc or .csv)
MACHINES = newdyn.catalog.machines(MEASUREMENTS)
# what a machine's diagnosis writes that a target asks for
MACHINE_FILES = ["verdict.json", "verdict.html", "figures/machine.png"]
# hidden set of machines -> machine -> its recordings' names, known from the set's seed before any draw
HIDDEN_MACHINES = {
    name: newdyn.hidden_sets.recording_names(name, spec) for name, spec in HIDDEN_SETS.items() if "recordings" in spec
}


def diagnosis_root(root, name):
    return f"{root}/diagnosis/{name}"


def measurement_file(wildcards):
    """A diagnosis's input file: the user's file, or a hidden set's drawn measurement."""
    if wildcards.root == "results":
        if wildcards.name not in MEASUREMENTS:
            raise ValueError(f"no good measurement measurements/{wildcards.name}.nc or .csv (see the lines above)")
        return MEASUREMENTS[wildcards.name]
    return f"{wildcards.root}/measurements/{wildcards.name}.nc"


def machine_inputs(wildcards):
    """A machine's recordings and each one's own verdict, in the same order: a user's folder in measurements/, or a
    hidden set's drawn machine."""
    if wildcards.root == "results":
        names, files = MACHINES[wildcards.machine], MEASUREMENTS
    else:
        names = HIDDEN_MACHINES[wildcards.root.removeprefix("results/")][wildcards.machine]
        files = {name: f"{wildcards.root}/measurements/{name}.nc" for name in names}
    return {
        "recordings": [files[name] for name in names],
        "verdicts": [f"{wildcards.root}/diagnosis/{name}/verdict.json" for name in names],
    }


def recording_conditions(wildcards):
    """The conditions.csv beside a user's recording, when there is one: its operating condition may come from it."""
    if wildcards.root != "results" or wildcards.name not in MEASUREMENTS:
        return []
    table = Path(MEASUREMENTS[wildcards.name]).parent / newdyn.measurement_files.CONDITIONS
    return [str(table)] if table.is_file() else []


def study_grids(wildcards):
    """The default study's coarse grids: the diagnosis reuses them when the measurement's condition is theirs."""
    if "default" not in VARIANTS:
        return []
    return expand("results/default/calibration/grids/{parameter}.nc", parameter=_grid_parameters(config))


def _diagnosis_settings():
    return {
        "rig": config["rig"],
        "operating": config["operating"],
        "sampling": _sampling_spec(config),
        "diagnosis": config["diagnosis"],
        "calibration": {key: config["calibration"][key] for key in ("parameters", "chi2_max", "refine_points", "mcmc")},
        "simulation": {"max_step": config["simulation"]["max_step"]},
        "effects": EFFECTS,
    }


def diagnosis_spec(wildcards):
    return newdyn.study.canonical_json(_diagnosis_settings())


def machine_spec(wildcards):
    """A diagnosis's settings and the rig's operating range, where the machine's verdict looks for the next condition."""
    return newdyn.study.canonical_json({**_diagnosis_settings(), "operating_range": config.get("operating_range", {})})


def hidden_cases(set_name):
    return newdyn.hidden_sets.case_names(set_name, HIDDEN_SETS[set_name]["cases"])


def diagnosis_targets(root, names):
    return expand("{root}/diagnosis/{name}/verdict.{kind}", root=root, name=names, kind=["json", "html"]) + expand(
        "{root}/diagnosis/{name}/figures/{figure}.png", root=root, name=names, figure=DIAGNOSIS_FIGURES
    )


def hidden_spec(wildcards):
    """What draws and simulates a hidden set: its name, cases and seed (not the other sets'), the draw's
    ranges, the rig and the record; for a set seen through instruments, their datasheets and the compared
    channels."""
    instruments = HIDDEN_SETS[wildcards.set].get("instruments", False)
    return newdyn.study.canonical_json(
        {
            "set": wildcards.set,
            "hidden": {**config["hidden"], "sets": {wildcards.set: HIDDEN_SETS[wildcards.set]}},
            "values": newdyn.study.base_values(config),
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
            **(
                {
                    "operating_range": config["operating_range"],
                    "channels": config["diagnosis"]["channels"],
                }
                if wildcards.set in HIDDEN_MACHINES
                else {}
            ),
        }
    )


def hidden_targets(set_name):
    """A hidden set's diagnoses, their figures and its score, if the set is configured; a machine set's machines'
    verdicts and its score."""
    if set_name not in HIDDEN_SETS:
        return []
    root = f"results/{set_name}"
    score = [f"{root}/score.json", f"{root}/blind_test.png"]
    if set_name in HIDDEN_MACHINES:
        return expand("{root}/diagnosis/{machine}/verdict.json", root=root, machine=HIDDEN_MACHINES[set_name]) + score
    return diagnosis_targets(root, hidden_cases(set_name)) + score


def hidden_recording_verdicts(wildcards):
    """A machine set's recordings' own verdicts, scored beside the machines'; none for a set of single files."""
    machines = HIDDEN_MACHINES.get(wildcards.set, {})
    return [f"results/{wildcards.set}/diagnosis/{name}/verdict.json" for names in machines.values() for name in names]
