# newdyn: find new dynamics in machines. Run: snakemake --cores 2
# Change a few settings: snakemake --cores 2 --configfile my.yaml (merged over config/config.yaml: its mappings key by
# key, its lists whole); a study of its own: add --replace-workflow-config (my.yaml then holds every section).
from snakemake.utils import min_version

min_version("9.0")


report: "workflow/report/workflow.rst"


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/noise.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/compare.smk"
include: "workflow/rules/summary.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/diagnose.smk"
include: "workflow/rules/hidden.smk"


rule all:
    default_target: True
    input:
        simulation_targets(),
        all_calibration_targets(),
        expand("results/{variant}/comparison/hellinger.nc", variant=VARIANTS),
        "results/summary.csv",
        figure_targets(),
        diagnosis_targets("results", list(MEASUREMENTS)),
        expand("results/diagnosis/{machine}/{file}", machine=MACHINES, file=MACHINE_FILES),
        hidden_targets(STUDY_HIDDEN_SET),


# Only the user's own files in measurements/: each file's verdict and figures, each machine folder's verdict.
rule measurements:
    input:
        diagnosis_targets("results", list(MEASUREMENTS)),
        expand("results/diagnosis/{machine}/{file}", machine=MACHINES, file=MACHINE_FILES),


rule blind:
    input:
        hidden_targets("blind"),


# At the end of a run, what each of the user's measurements and machines was found to be.
onsuccess:
    for line in newdyn.verdicts.statements(
        [f"results/diagnosis/{name}/verdict.json" for name in [*MEASUREMENTS, *MACHINES]]
    ):
        print(line)
