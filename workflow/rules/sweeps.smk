# Sweeps (conf/sweep/*.yaml): each point an ordinary fine-tuning or pretraining job plus its evaluation, under
# results/<scale>/sweeps/<sweep>/<point>/; a table and a figure per sweep; `snakemake sweep_<name>` runs one.


rule sweep_finetune:
    input:
        fit=lambda wc: TREE.subject(PLAN.sweeps[wc.sweep].subject, "fit_rgb.npz"),
        masks=lambda wc: TREE.subject(PLAN.sweeps[wc.sweep].subject, "masks.npz"),
        model=lambda wc: TREE.pretrain(PLAN.sweeps[wc.sweep].init, "model.pt"),
        tracking=TRACKING_READY,
    output:
        model=TREE.sweep("{sweep}", "{point}", "model.pt"),
        train=TREE.sweep("{sweep}", "{point}", "train.json"),
    wildcard_constraints:
        sweep=sweep_names("finetune"),
    log:
        LOG_TREE.sweep("{sweep}", "{point}.log"),
    params:
        **step_params(
            "avatarlab.avatar.finetune",
            extra=lambda wc: (f"finetune={PLAN.sweeps[wc.sweep].recipe}", *PLAN.sweep_point(wc.sweep, wc.point).overrides),
            values=lambda wc, input, output: {**PLAN.finetune_values(PLAN.sweep_avatar(wc.sweep), output.model),
                                              "finetune.init_model": input.model, **PLAN.sweep_tags(wc.sweep, wc.point)},
            run_dir=lambda wc: TREE.sweep(wc.sweep, wc.point, ".hydra")),
    threads: step_threads("finetune")
    resources:
        **step_resources("finetune"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.finetune {params.args} threads={threads} > {log} 2>&1"


rule sweep_evaluate_avatar:
    """A fine-tuning point scored like every avatar (same test frames and baselines; the point's overrides are not
    passed: every point is scored the same way)."""
    input:
        model=TREE.sweep("{sweep}", "{point}", "model.pt"),
        fit=lambda wc: TREE.subject(PLAN.sweeps[wc.sweep].subject, "fit_rgb.npz"),
        masks=lambda wc: TREE.subject(PLAN.sweeps[wc.sweep].subject, "masks.npz"),
        landmarks=lambda wc: TREE.subject(PLAN.sweeps[wc.sweep].subject, "landmarks.npz"),
        tracking=TRACKING_READY,
    output:
        report=TREE.sweep("{sweep}", "{point}", "eval.json"),
        frames=TREE.sweep("{sweep}", "{point}", "test_frames.png"),
    wildcard_constraints:
        sweep=sweep_names("finetune"),
    log:
        LOG_TREE.sweep("{sweep}", "{point}_eval.log"),
    params:
        **step_params(
            "avatarlab.avatar.evaluate", extra=lambda wc: (f"finetune={PLAN.sweeps[wc.sweep].recipe}",),
            values=lambda wc, input, output: {**PLAN.finetune_values(PLAN.sweep_avatar(wc.sweep), input.model),
                                              "evaluate.model": input.model, "evaluate.out": output.report},
            run_dir=lambda wc: TREE.sweep(wc.sweep, wc.point, ".hydra", "eval")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.evaluate {params.args} threads={threads} > {log} 2>&1"


rule sweep_pretrain:
    input:
        **PLAN.real_set(),
        tracking=TRACKING_READY,
        parent=lambda wc: ([TREE.pretrain(PLAN.sweeps[wc.sweep].parent, "model.pt")]
                           if PLAN.sweeps[wc.sweep].parent else []),
    output:
        model=TREE.sweep("{sweep}", "{point}", "model.pt"),
        train=TREE.sweep("{sweep}", "{point}", "train.json"),
    wildcard_constraints:
        sweep=sweep_names("pretrain"),
    log:
        LOG_TREE.sweep("{sweep}", "{point}.log"),
    params:
        **step_params(
            "avatarlab.pretrain.train",
            extra=lambda wc: (f"strategy={PLAN.sweeps[wc.sweep].strategy}", *PLAN.sweep_point(wc.sweep, wc.point).overrides),
            values=lambda wc, input, output: {
                "pretrain.name": f"{wc.sweep}/{wc.point}", "pretrain.out_dir": str(Path(output.model).parent),
                "pretrain.real_subject_dir": str(Path(input.fit).parent),
                **({"pretrain.init_model": input.parent[0]} if input.parent else {}), **PLAN.sweep_tags(wc.sweep, wc.point)},
            run_dir=lambda wc: TREE.sweep(wc.sweep, wc.point, ".hydra")),
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.train {params.args} threads={threads} > {log} 2>&1"


rule sweep_evaluate_pretrained:
    input:
        model=TREE.sweep("{sweep}", "{point}", "model.pt"),
        **PLAN.real_set(),
        tracking=TRACKING_READY,
    output:
        report=TREE.sweep("{sweep}", "{point}", "eval.json"),
        samples=TREE.sweep("{sweep}", "{point}", "eval_samples.png"),
    wildcard_constraints:
        sweep=sweep_names("pretrain"),
    log:
        LOG_TREE.sweep("{sweep}", "{point}_eval.log"),
    params:
        **step_params("avatarlab.pretrain.evaluate", values=lambda wc, input, output: {
            "evaluate.model": input.model, "evaluate.out": output.report,
            "evaluate.real_subject_dir": str(Path(input.fit).parent)},
            run_dir=lambda wc: TREE.sweep(wc.sweep, wc.point, ".hydra", "eval")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.evaluate {params.args} threads={threads} > {log} 2>&1"


rule sweep_table:
    """One row per setting (mean +- 95 % CI over its seeds) and a figure of the metric against each swept value."""
    input:
        evals=lambda wc: PLAN.sweep_point_evals(wc.sweep),
        spec=lambda wc: str(PLAN.sweep_files / f"{wc.sweep}.yaml"),
    output:
        table=TREE.sweep("{sweep}", "table.md"),
        csv=TREE.sweep("{sweep}", "table.csv"),
        figure=report(TREE.sweep("{sweep}", "figure.png"), caption="../report/sweep.rst", category="Sweeps",
                      subcategory="{sweep}"),
    log:
        LOG_TREE.sweep("{sweep}", "table.log"),
    params:
        code=STEPS.code("avatarlab.report.sweep_report"),
        folder=lambda wc: PLAN.sweep_dir(wc.sweep),
        seeds=lambda wc: "" if config.get("sweep_seeds") is None else f"--seeds {int(config['sweep_seeds'])}",
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.report.sweep_report --sweep {input.spec:q} --dir {params.folder:q} {params.seeds} > {log} 2>&1"


for _sweep in PLAN.sweeps:

    rule:
        name:
            f"sweep_{_sweep}"
        input:
            PLAN.sweep_outputs(_sweep),
        default_target: False
        localrule: True
