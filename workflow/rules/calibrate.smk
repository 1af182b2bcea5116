rule grid_models:
    output:
        "results/{variant}/calibration/grids/{parameter}.nc",
    log:
        "results/logs/grid_models/{variant}/{parameter}.log",
    benchmark:
        "results/benchmarks/grid_models/{variant}/{parameter}.tsv"
    # First, on one thread (below): a two-thread job waits for both cores to be free, which with the
    # study's one-thread jobs queued is near the end, and every grid calibration and diagnosis waits on it.
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
        spec=grid_models_spec,
        code=code_hash("grid-models"),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn grid-models --spec {params.spec:q} "
        "--code-hash {params.code} --output {output} > {log} 2>&1"


# One job per measurement calibrates every parameter of its variant on its grid, as a job's start and imports cost
# more than one calibration; a variant's parameters fix the job's outputs, so each variant has its rule. A change of
# one parameter's prior or grid reruns every measurement's job, and so everything that reads its files.
for variant, variant_config in VARIANTS.items():

    rule:
        name:
            f"calibrate_grid_{variant}"
        input:
            measurement="results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
            grids=grid_files(variant_config),
        output:
            grid_calibration_files(variant_config),
        log:
            "results/logs/calibrate_grid/{variant}/{scenario}/snr{snr}_seed{seed}.log",
        benchmark:
            "results/benchmarks/calibrate_grid/{variant}/{scenario}/snr{snr}_seed{seed}.tsv"
        wildcard_constraints:
            variant=re.escape(variant),
        group:
            SCENARIO_GROUP
        conda:
            "../envs/newdyn.yaml"
        threads: 1
        resources:
            mem_mb=per_attempt(1024),
            runtime=per_attempt(10),
        params:
            spec=grid_calibration_spec,
            code=code_hash("calibrate-grid"),
        shell:
            "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn calibrate-grid --measurement {input.measurement} "
            "--grids {input.grids} --spec {params.spec:q} --code-hash {params.code} --outputs {output} > {log} 2>&1"


# One job per measurement runs its variant's MCMC calibrations one after the other (each parameter's, then the joint
# one), as a job's start and imports cost about as much as one run; as for the grid calibrations, each variant has its
# rule.
for variant, variant_config in VARIANTS.items():
    if not newdyn.study.mcmc_runs(variant_config):
        continue

    rule:
        name:
            f"calibrate_mcmc_{variant}"
        input:
            measurement="results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
            grid_results=mcmc_grid_results(variant_config),
        output:
            mcmc_calibration_files(variant_config),
        log:
            "results/logs/calibrate_mcmc/{variant}/{scenario}/snr{snr}_seed{seed}.log",
        benchmark:
            "results/benchmarks/calibrate_mcmc/{variant}/{scenario}/snr{snr}_seed{seed}.tsv"
        wildcard_constraints:
            variant=re.escape(variant),
        group:
            SCENARIO_GROUP
        conda:
            "../envs/newdyn.yaml"
        threads: 1
        resources:
            mem_mb=per_attempt(1024),
            runtime=per_attempt(30),
        params:
            spec=mcmc_spec,
            code=code_hash("calibrate-mcmc"),
        shell:
            "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn calibrate-mcmc --measurement {input.measurement} "
            "--grid-results {input.grid_results} --spec {params.spec:q} --code-hash {params.code} "
            "--outputs {output} > {log} 2>&1"
