rule summarize:
    input:
        calibration_targets(),
    output:
        "results/summary.csv",
    log:
        "results/logs/summarize.log",
    benchmark:
        "results/benchmarks/summarize.tsv"
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    params:
        code=SUMMARY_CODE,
    shell:
        "newdyn summarize --code-hash {params.code} --output {output} {input} > {log} 2>&1"
