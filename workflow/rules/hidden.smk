# Hidden-effect measurements: drawn from a seed (the truth goes into one file only), written as
# measurement files without it, diagnosed by the same rules as a user's file, and only then scored.
wildcard_constraints:
    set="|".join(HIDDEN_SETS),


rule hidden_draw:
    output:
        "results/{set}/truth.json",
    log:
        "results/logs/hidden_draw/{set}.log",
    benchmark:
        "results/benchmarks/hidden_draw/{set}.tsv"
    # As the diagnoses they feed: a hidden case's diagnosis, the longest job, starts beside the calibrations.
    priority: 1
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        spec=hidden_spec,
        code=code_hash("hidden-draw", effect_files()),
    shell:
        "newdyn hidden-draw --spec {params.spec:q} --code-hash {params.code} --output {output} > {log} 2>&1"


rule hidden_measurement:
    input:
        "results/{set}/truth.json",
    output:
        "results/{set}/measurements/{name}.nc",
    log:
        "results/logs/hidden_measurement/{set}/{name}.log",
    benchmark:
        "results/benchmarks/hidden_measurement/{set}/{name}.tsv"
    priority: 1
    group:
        CASE_GROUP
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        spec=hidden_spec,
        code=code_hash("hidden-measurement", effect_files()),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn hidden-measurement --truth {input} --case {wildcards.name} "
        "--spec {params.spec:q} --code-hash {params.code} --output {output} > {log} 2>&1"


rule hidden_score:
    input:
        truth="results/{set}/truth.json",
        verdicts=lambda wildcards: expand(
            "results/{set}/diagnosis/{name}/verdict.json", set=wildcards.set, name=hidden_cases(wildcards.set)
        ),
        recordings=hidden_recording_verdicts,
    output:
        score="results/{set}/score.json",
        table=report(
            "results/{set}/cases.csv",
            caption="../report/hidden_table.rst",
            category=category("Blind test"),
            subcategory="{set}",
        ),
        png=report(
            "results/{set}/blind_test.png",
            caption="../report/hidden_score.rst",
            category=category("Blind test"),
            subcategory="{set}",
        ),
        pdf="results/{set}/blind_test.pdf",
    log:
        "results/logs/hidden_score/{set}.log",
    benchmark:
        "results/benchmarks/hidden_score/{set}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        chi2_max=config["calibration"]["chi2_max"],
        code=code_hash("hidden-score", effect_files()),
        effects=" ".join(f"--effect {name}" for name in EFFECTS),
    shell:
        "newdyn hidden-score --truth {input.truth} --chi2-max {params.chi2_max} --code-hash {params.code} {params.effects} "
        "--output {output.score} --table {output.table} --figure {output.png} {input.verdicts} "
        "--recordings {input.recordings} > {log} 2>&1"
