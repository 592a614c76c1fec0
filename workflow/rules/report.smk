# The report: tables and figures from every run's train/eval files (results/<scale>/report/).


rule report_tables:
    input:
        PLAN.preprocessing_outputs(),
        PLAN.pretrain_outputs(),
        PLAN.avatar_outputs(),
        PLAN.speech_outputs(),
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
        **step_params("avatarlab.evaluate.report", values=lambda wc, input, output: {
            "report.results_dir": str(Path(output.summary).parent.parent),
            "report.out_dir": str(Path(output.summary).parent), "report.final_recipe": PLAN.final_recipe},
            run_dir=lambda wc: f"{RESULTS}/report/.hydra"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.forkserver avatarlab.evaluate.report {params.args} > {log} 2>&1"
