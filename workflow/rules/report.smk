# The report: tables and figures from every run's train/eval files (results/<scale>/report/).


# The report reads the results this configuration plans, never a folder left over from an older one: this rule
# hands it the list (a param: it is rewritten when the plan changes, not when a result does).
rule report_inputs:
    output:
        planned=TREE.report("planned.json"),
    params:
        files=PLAN.report_inputs(),
    log:
        LOG_TREE.report("report_inputs.log"),
    localrule: True
    run:
        write_planned(output.planned, params.files, TREE.root, log=log[0])


rule report_tables:
    input:
        PLAN.report_inputs(),
        planned=TREE.report("planned.json"),
    output:
        index=report(TREE.report("README.md"), caption="../report/report.rst", category="Report"),
        summary=TREE.report("summary.json"),
        table2=report(TREE.report("tables", "table2_comparison.csv"), caption="../report/report.rst",
                      category="Report"),
        figure=report(TREE.report("figures", "time_vs_quality.png"), caption="../report/time_vs_quality.rst",
                      category="Report"),
    log:
        LOG_TREE.report("report.log"),
    params:
        **step_params("avatarlab.report.build", values=lambda wc, input, output: {
            "report.results_dir": str(Path(output.summary).parent.parent),
            "report.out_dir": str(Path(output.summary).parent), "report.final_recipe": PLAN.final_recipe,
            "report.planned": input.planned},
            run_dir=lambda wc: TREE.report(".hydra")),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.report.build {params.args} > {log} 2>&1"
