# Figures (PNG for the report, PDF beside each) and the report's grouping: one category per stage. One job per stage
# draws every figure of it across the study, so that matplotlib (and for MCMC, ArviZ) is imported once per process
# rather than for every figure; a change of any of a stage's inputs redraws the whole stage, which costs little once
# imported.  Each stage draws on one core: a job of two threads waits until both cores are free, which in a study
# comes only once every job of one thread has ended, and its second process would pay the imports again.
# Captions cannot name a figure's wildcards: its labels (scenario, SNR, seed) and subcategory (variant) do.


# posteriors: prior, likelihood and posterior of each measurement's grid calibrations, and the paper's
# Figs. 3 and 4 (drawn the same way)
rule plot_posteriors:
    input:
        figure_inputs("posteriors"),
    output:
        figure_files("posteriors"),
    log:
        "results/logs/plot_posteriors.log",
    benchmark:
        "results/benchmarks/plot_posteriors.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        figures=figure_plan("posteriors"),
        code=code_hash("plot"),
    shell:
        "newdyn plot posteriors --figures {params.figures:q} --code-hash {params.code} > {log} 2>&1"


# overlays: each measurement against its best fits, in time and spectrum
rule plot_overlays:
    input:
        figure_inputs("overlays"),
    output:
        figure_files("overlays"),
    log:
        "results/logs/plot_overlays.log",
    benchmark:
        "results/benchmarks/plot_overlays.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        figures=figure_plan("overlays"),
        code=code_hash("plot"),
    shell:
        "newdyn plot overlays --figures {params.figures:q} --code-hash {params.code} > {log} 2>&1"


# mcmc: trace and rank plots of each measurement's MCMC calibrations
rule plot_mcmc:
    input:
        figure_inputs("mcmc"),
    output:
        figure_files("mcmc"),
    log:
        "results/logs/plot_mcmc.log",
    benchmark:
        "results/benchmarks/plot_mcmc.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        figures=figure_plan("mcmc"),
        code=code_hash("plot"),
    shell:
        "newdyn plot mcmc --figures {params.figures:q} --code-hash {params.code} > {log} 2>&1"


# signatures: the Hellinger matrices of each variant, SNR and seed
rule plot_signatures:
    input:
        figure_inputs("signatures"),
    output:
        figure_files("signatures"),
    log:
        "results/logs/plot_signatures.log",
    benchmark:
        "results/benchmarks/plot_signatures.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        figures=figure_plan("signatures"),
        code=code_hash("plot"),
    shell:
        "newdyn plot signatures --figures {params.figures:q} --code-hash {params.code} > {log} 2>&1"


# summary: Hellinger distance to healthy and reduced χ² of every grid calibration
rule plot_summary:
    input:
        figure_inputs("summary"),
    output:
        figure_files("summary"),
    log:
        "results/logs/plot_summary.log",
    benchmark:
        "results/benchmarks/plot_summary.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        figures=figure_plan("summary"),
        code=code_hash("plot"),
    shell:
        "newdyn plot summary --figures {params.figures:q} --code-hash {params.code} > {log} 2>&1"
