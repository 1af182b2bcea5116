rule compare:
    input:
        lambda wildcards: calibration_targets(wildcards.variant, methods=["grid"]),
    output:
        "results/{variant}/comparison/hellinger.nc",
    log:
        "results/logs/compare/{variant}.log",
    benchmark:
        "results/benchmarks/compare/{variant}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("compare"),
    shell:
        "newdyn compare --code-hash {params.code} --output {output} {input} > {log} 2>&1"
