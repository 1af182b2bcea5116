# On a batch system a scenario is one job: its simulation, its noisy copies and their calibrations, the rules of
# group "scenario" (one group job per scenario; a local run ignores groups). Each job a batch system runs pays its
# queue, its start and the wait for the next status check, which cost more than most of these jobs' work.
rule simulate:
    output:
        "results/{variant}/simulations/{scenario}/clean.nc",
    log:
        "results/logs/simulate/{variant}/{scenario}.log",
    benchmark:
        "results/benchmarks/simulate/{variant}/{scenario}.tsv"
    group:
        "scenario"
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        spec=simulation_spec,
        code=simulation_code,
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn simulate --spec {params.spec:q} "
        "--code-hash {params.code} --output {output} > {log} 2>&1"
