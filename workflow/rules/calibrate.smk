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


rule calibrate_mcmc:
    input:
        measurement="results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
        grid_result="results/{variant}/calibration/{scenario}/{parameter}/snr{snr}_seed{seed}_grid.nc",
    output:
        "results/{variant}/calibration/{scenario}/{parameter}/snr{snr}_seed{seed}_mcmc.nc",
    log:
        "results/logs/calibrate_mcmc/{variant}/{scenario}/{parameter}/snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/calibrate_mcmc/{variant}/{scenario}/{parameter}/snr{snr}_seed{seed}.tsv"
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(15),
    params:
        spec=mcmc_spec,
        code=code_hash("calibrate-mcmc"),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn calibrate-mcmc --measurement {input.measurement} "
        "--grid-result {input.grid_result} --spec {params.spec:q} --code-hash {params.code} "
        "--output {output} > {log} 2>&1"


rule calibrate_joint:
    input:
        measurement="results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
        grid_results=lambda wildcards: expand(
            "results/{{variant}}/calibration/{{scenario}}/{parameter}/snr{{snr}}_seed{{seed}}_grid.nc",
            parameter=study(wildcards)["calibration"]["joint"]["parameters"],
        ),
    output:
        "results/{variant}/calibration/{scenario}/joint/snr{snr}_seed{seed}_mcmc.nc",
    log:
        "results/logs/calibrate_joint/{variant}/{scenario}/snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/calibrate_joint/{variant}/{scenario}/snr{snr}_seed{seed}.tsv"
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(20),
    params:
        spec=joint_spec,
        code=code_hash("calibrate-joint"),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn calibrate-joint --measurement {input.measurement} "
        "--grid-results {input.grid_results} --spec {params.spec:q} --code-hash {params.code} "
        "--output {output} > {log} 2>&1"
