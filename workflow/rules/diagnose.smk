# Diagnosis of one measurement (a user's file, or a hidden set's): verdict, model versions, figures.
# The same rules serve both; {root} is "results" for measurements/<name>, "results/<set>" for hidden sets.
# A regex of every machine's name, the user's and the hidden sets' (one that matches nothing when there is none).
MACHINE_NAMES = "|".join(map(re.escape, [*MACHINES, *(m for s in HIDDEN_MACHINES.values() for m in s)])) or "(?!)"
# A file's name, or a machine's recording's <machine>/<recording>.
MEASUREMENT_NAME = r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)?"


wildcard_constraints:
    root="|".join(["results"] + [f"results/{name}" for name in HIDDEN_SETS]),
    name=MEASUREMENT_NAME,
    machine=MACHINE_NAMES,


rule bank:
    input:
        grids=study_grids,
    output:
        "results/bank.nc",
    log:
        "results/logs/bank.log",
    benchmark:
        "results/benchmarks/bank.tsv"
    # First, as every diagnosis waits on it, on one thread: a two-thread job waits for both cores to be free, which
    # with the study's one-thread jobs queued is near the end, and the bank then heads a chain that ends the study.
    priority: 2
    group:
        LIBRARY_GROUP
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        spec=diagnosis_spec,
        code=code_hash("bank", effect_files()),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn bank --grids {input.grids} "
        "--spec {params.spec:q} --code-hash {params.code} --output {output} > {log} 2>&1"


rule diagnose:
    input:
        measurement=measurement_file,
        conditions=recording_conditions,
        grids=study_grids,
        bank="results/bank.nc",
    output:
        verdict="{root}/diagnosis/{name}/verdict.json",
        table=report(
            "{root}/diagnosis/{name}/model_versions.csv",
            caption="../report/diagnosis_table.rst",
            category=category("Diagnosis"),
            subcategory="{name}",
            labels={"measurement": "{name}", "figure": "model versions (table)"},
        ),
        netcdf="{root}/diagnosis/{name}/diagnosis.nc",
        posterior="{root}/diagnosis/{name}/effect_posterior.nc",
        discovery=directory("{root}/diagnosis/{name}/discovery"),
    log:
        "{root}/logs/diagnose/{name}.log",
    benchmark:
        "{root}/benchmarks/diagnose/{name}.tsv"
    # results/diagnosis/<machine>/verdict.json is the machine's, not a file's of that name (the catalog refuses such a
    # file): a machine's name is no file's, so Snakemake never asks this rule's input for one.
    wildcard_constraints:
        name=rf"(?!(?:{MACHINE_NAMES})/[^/]+$){MEASUREMENT_NAME}",
    # Its log's lines (each stage and fit as it ends) go to the terminal too, so that a long diagnosis can be watched.
    priority: 1
    group:
        CASE_GROUP
    conda:
        "../envs/newdyn.yaml"
    threads: diagnosis_threads
    resources:
        mem_mb=per_attempt(2048),
        runtime=per_attempt(120),
    params:
        spec=diagnosis_spec,
        code=code_hash("diagnose", effect_files()),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn diagnose --measurement {input.measurement} "
        "--grids {input.grids} --bank {input.bank} --spec {params.spec:q} --code-hash {params.code} "
        "--verdict {output.verdict} --table {output.table} "
        "--netcdf {output.netcdf} --posterior {output.posterior} --discovery {output.discovery} 2>&1 | tee {log}"


rule plot_diagnosis:
    input:
        verdict="{root}/diagnosis/{name}/verdict.json",
        netcdf="{root}/diagnosis/{name}/diagnosis.nc",
        posterior="{root}/diagnosis/{name}/effect_posterior.nc",
    output:
        **{
            figure: report(
                f"{{root}}/diagnosis/{{name}}/figures/{figure}.png",
                caption=f"../report/diagnosis_{figure}.rst",
                category=category("Diagnosis"),
                subcategory="{name}",
                labels={"measurement": "{name}", "figure": figure},
            )
            for figure in DIAGNOSIS_FIGURES
        },
        **{f"{figure}_pdf": f"{{root}}/diagnosis/{{name}}/figures/{figure}.pdf" for figure in DIAGNOSIS_FIGURES},
    log:
        "{root}/logs/plot_diagnosis/{name}.log",
    benchmark:
        "{root}/benchmarks/plot_diagnosis/{name}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot-diagnosis"),
    shell:
        "newdyn plot-diagnosis --verdict {input.verdict} --netcdf {input.netcdf} --posterior {input.posterior} "
        "--overlays {output.overlays} --residuals {output.residuals} --hypotheses {output.hypotheses} "
        "--error-fall {output.error_fall} --discovery {output.discovery} --effect-posterior {output.effect_posterior} "
        "--code-hash {params.code} > {log} 2>&1"


# The verdict of a file or of a machine, its statement first, as a page of the report.
rule verdict_page:
    input:
        "{root}/diagnosis/{name}/verdict.json",
    output:
        report(
            "{root}/diagnosis/{name}/verdict.html",
            caption="../report/diagnosis_verdict.rst",
            category=category("Diagnosis"),
            subcategory="{name}",
            labels={"measurement": "{name}", "figure": "verdict"},
        ),
    log:
        "{root}/logs/verdict_page/{name}.log",
    benchmark:
        "{root}/benchmarks/verdict_page/{name}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("verdict-page"),
    shell:
        "newdyn verdict-page --verdict {input} --output {output} --code-hash {params.code} > {log} 2>&1"


rule diagnose_machine:
    input:
        unpack(machine_inputs),
    output:
        verdict="{root}/diagnosis/{machine}/verdict.json",
        discovery=directory("{root}/diagnosis/{machine}/discovery"),
    log:
        "{root}/logs/diagnose_machine/{machine}.log",
    benchmark:
        "{root}/benchmarks/diagnose_machine/{machine}.tsv"
    conda:
        "../envs/newdyn.yaml"
    threads: 2
    resources:
        mem_mb=per_attempt(2048),
        runtime=per_attempt(60),
    params:
        spec=machine_spec,
        code=code_hash("diagnose-machine", effect_files()),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn diagnose-machine --name {wildcards.machine} "
        "--recordings {input.recordings} --verdicts {input.verdicts} --spec {params.spec:q} --code-hash {params.code} "
        "--output {output.verdict} --discovery {output.discovery} 2>&1 | tee {log}"


rule plot_machine:
    input:
        "{root}/diagnosis/{machine}/verdict.json",
    output:
        png=report(
            "{root}/diagnosis/{machine}/figures/machine.png",
            caption="../report/diagnosis_machine.rst",
            category=category("Diagnosis"),
            subcategory="{machine}",
            labels={"measurement": "{machine}", "figure": "machine"},
        ),
        pdf="{root}/diagnosis/{machine}/figures/machine.pdf",
    log:
        "{root}/logs/plot_machine/{machine}.log",
    benchmark:
        "{root}/benchmarks/plot_machine/{machine}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot-machine"),
    shell:
        "newdyn plot-machine --verdict {input} --output {output.png} --code-hash {params.code} > {log} 2>&1"
