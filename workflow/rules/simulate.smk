rule simulate:
    output:
        "results/simulations/{scenario}/clean.nc",
    params:
        spec=simulation_spec,
        code=SIMULATION_CODE,
    log:
        "results/logs/simulate/{scenario}.log",
    benchmark:
        "results/benchmarks/simulate/{scenario}.tsv"
    threads: 1
    conda:
        "../envs/newdyn.yaml"
    shell:
        "NUMBA_NUM_THREADS={threads} newdyn simulate --spec {params.spec:q} "
        "--code-hash {params.code} --output {output} > {log} 2>&1"
