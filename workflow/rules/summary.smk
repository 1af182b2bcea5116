rule summarize:
    input:
        all_calibration_targets(),
    output:
        report("results/summary.csv", caption="../report/summary_table.rst", category=category("Summary")),
    log:
        "results/logs/summarize.log",
    benchmark:
        "results/benchmarks/summarize.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    threads: 1
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("summarize"),
    shell:
        "newdyn summarize --code-hash {params.code} --output {output} {input} > {log} 2>&1"
