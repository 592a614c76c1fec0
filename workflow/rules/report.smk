# The report: tables and figures from every run's metrics (results/<scale>/report/).


rule report_tables:
    input:
        preprocessing_outputs(),
        pretrain_outputs(),
        avatar_outputs(),
        speech_outputs(),
        code=module_sources("avatarlab.evaluate.report"),
    output:
        index=report(f"{RESULTS}/report/README.md", caption="../report/report.rst", category="Report"),
        summary=f"{RESULTS}/report/summary.json",
        table2=report(f"{RESULTS}/report/tables/table2_comparison.csv", caption="../report/report.rst",
                      category="Report"),
        figure=report(f"{RESULTS}/report/figures/time_vs_quality.png", caption="../report/time_vs_quality.rst",
                      category="Report"),
    log:
        f"{LOGS}/report/report.log",
    params:
        settings=lambda wc: settings("report", modules=("avatarlab.evaluate.report",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/report/.hydra"),
        final=lambda wc: FINAL_RECIPE,
        results=lambda wc, output: str(Path(output.summary).parent.parent),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.evaluate.report {params.hydra} 'report.results_dir={params.results}'"
        " 'report.out_dir={params.results}/report' 'report.final_recipe={params.final}' > {log} 2>&1"
