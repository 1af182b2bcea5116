rule add_noise:
    input:
        "results/simulations/{scenario}/clean.nc",
    output:
        "results/simulations/{scenario}/snr{snr}_seed{seed}.nc",
    params:
        code=NOISE_CODE,
    log:
        "results/logs/add_noise/{scenario}/snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/add_noise/{scenario}/snr{snr}_seed{seed}.tsv"
    threads: 1
    conda:
        "../envs/newdyn.yaml"
    shell:
        "NUMBA_NUM_THREADS={threads} newdyn add-noise --input {input} --output {output} "
        "--snr-db {wildcards.snr} --seed {wildcards.seed} --code-hash {params.code} > {log} 2>&1"
