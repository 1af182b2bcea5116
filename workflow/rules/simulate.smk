rule simulate:
    output:
        "results/{variant}/simulations/{scenario}/clean.nc",
    log:
        "results/logs/simulate/{variant}/{scenario}.log",
    benchmark:
        "results/benchmarks/simulate/{variant}/{scenario}.tsv"
    group:
        SCENARIO_GROUP
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
