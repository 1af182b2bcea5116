# Figures (PNG for the report, PDF beside each) and the report's grouping: one category per stage.
rule plot_posteriors:
    input:
        _grid_results,
    output:
        **_figure(
            "results/{variant}/figures/posteriors/{scenario}_snr{snr}_seed{seed}",
            "posteriors",
            "2 Calibration",
            scenario="{scenario}",
            snr_dB="{snr}",
            seed="{seed}",
        ),
    log:
        "results/logs/plot_posteriors/{variant}/{scenario}_snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/plot_posteriors/{variant}/{scenario}_snr{snr}_seed{seed}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot"),
    shell:
        "newdyn plot posteriors --code-hash {params.code} --output {output.png} {input} > {log} 2>&1"


rule plot_paper_figure:
    input:
        lambda wildcards: expand(
            "results/{{variant}}/calibration/{scenario}/{parameter}/snr{{snr}}_seed{{seed}}_grid.nc",
            scenario=PAPER_FIGURES[wildcards.figure][0],
            parameter=PAPER_FIGURES[wildcards.figure][1],
        ),
    output:
        png=report(
            "results/{variant}/figures/{figure}_snr{snr}_seed{seed}.png",
            caption="../report/paper_figures.rst",
            category="1 The paper's figures",
            subcategory="{variant}",
            labels={"figure": "{figure}", "snr_dB": "{snr}", "seed": "{seed}"},
        ),
        pdf="results/{variant}/figures/{figure}_snr{snr}_seed{seed}.pdf",
    log:
        "results/logs/plot_paper_figure/{variant}/{figure}_snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/plot_paper_figure/{variant}/{figure}_snr{snr}_seed{seed}.tsv"
    wildcard_constraints:
        figure="|".join(PAPER_FIGURES),
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot"),
    shell:
        "newdyn plot posteriors --code-hash {params.code} --output {output.png} {input} > {log} 2>&1"


rule plot_overlays:
    input:
        measurement="results/{variant}/simulations/{scenario}/snr{snr}_seed{seed}.nc",
        grid_results=_grid_results,
    output:
        **_figure(
            "results/{variant}/figures/overlays/{scenario}_snr{snr}_seed{seed}",
            "overlays",
            "3 Model vs data",
            scenario="{scenario}",
            snr_dB="{snr}",
            seed="{seed}",
        ),
    log:
        "results/logs/plot_overlays/{variant}/{scenario}_snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/plot_overlays/{variant}/{scenario}_snr{snr}_seed{seed}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot"),
    shell:
        "newdyn plot overlays --code-hash {params.code} --measurement {input.measurement} "
        "--output {output.png} {input.grid_results} > {log} 2>&1"


rule plot_mcmc:
    input:
        lambda wildcards: expand(
            "results/{{variant}}/calibration/{{scenario}}/{parameter}/snr{{snr}}_seed{{seed}}_mcmc.nc",
            parameter=mcmc_runs(study(wildcards)),
        ),
    output:
        **_figure(
            "results/{variant}/figures/mcmc/{scenario}_snr{snr}_seed{seed}",
            "mcmc",
            "4 MCMC diagnostics",
            scenario="{scenario}",
            snr_dB="{snr}",
            seed="{seed}",
        ),
    log:
        "results/logs/plot_mcmc/{variant}/{scenario}_snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/plot_mcmc/{variant}/{scenario}_snr{snr}_seed{seed}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot"),
    shell:
        "newdyn plot mcmc --code-hash {params.code} --output {output.png} {input} > {log} 2>&1"


rule plot_signatures:
    input:
        "results/{variant}/comparison/hellinger.nc",
    output:
        **_figure(
            "results/{variant}/figures/signatures_snr{snr}_seed{seed}",
            "signatures",
            "5 Comparison",
            snr_dB="{snr}",
            seed="{seed}",
        ),
    log:
        "results/logs/plot_signatures/{variant}/snr{snr}_seed{seed}.log",
    benchmark:
        "results/benchmarks/plot_signatures/{variant}/snr{snr}_seed{seed}.tsv"
    localrule: True
    conda:
        "../envs/newdyn.yaml"
    resources:
        mem_mb=per_attempt(1024),
        runtime=per_attempt(10),
    params:
        code=code_hash("plot"),
    shell:
        "newdyn plot signatures --code-hash {params.code} --snr-db {wildcards.snr} --seed {wildcards.seed} "
        "--output {output.png} {input} > {log} 2>&1"


rule plot_summary:
    input:
        "results/summary.csv",
    output:
        png=report("results/figures/summary_hellinger.png", caption="../report/summary.rst", category="0 Summary"),
        chi2_png=report("results/figures/summary_chi2.png", caption="../report/summary.rst", category="0 Summary"),
        pdf="results/figures/summary_hellinger.pdf",
        chi2_pdf="results/figures/summary_chi2.pdf",
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
        code=code_hash("plot"),
    shell:
        "newdyn plot summary --code-hash {params.code} --output {output.png} --chi2-output {output.chi2_png} "
        "{input} > {log} 2>&1"
