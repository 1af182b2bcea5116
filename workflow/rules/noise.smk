rule add_noise:
    input:
        "results/{variant}/simulations/{scenario}/clean.nc",
    output:
        "results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
    log:
        "results/logs/add_noise/{variant}/{scenario}/snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/add_noise/{variant}/{scenario}/snr{snr}_seed{seed}.tsv"
    group:
        SCENARIO_GROUP
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("add-noise"),
    shell:
        "NUMBA_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} newdyn add-noise --input {input} --output {output} "
        "--snr-db {wildcards.snr} --seed {wildcards.seed} --code-hash {params.code} > {log} 2>&1"
