# Pretraining of the parametric head model: the real image set, 2 alpha + 12 beta models, the renderer experiment,
# and each model's evaluation against its trivial baselines.


rule init_tracking:
    output:
        TRACKING_READY,
    log:
        TRACKING_LOG,
    priority: PLAN.step_priority("init_tracking")
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.runtime.tracking init results {output} > {log} 2>&1"


rule synthesize_portraits:
    output:
        images=directory(TREE.subject("{subject}", "input", "images")),
        truth=TREE.subject("{subject}", "input", "portraits_truth.npz"),
    log:
        LOG_TREE.subject("{subject}", "portraits.log"),
    params:
        **step_params("avatarlab.pretrain.portraits", values=lambda wc, input, output: {
            "subject.name": wc.subject, "subject.images_out": output.images, "subject.truth_out": output.truth},
            run_dir=lambda wc: TREE.subject(wc.subject, ".hydra", "portraits")),
    priority: PLAN.step_priority("synthesize_portraits")
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.portraits {params.args} threads={threads} > {log} 2>&1"


rule pretrain_alpha:
    input:
        **PLAN.real_set(),
        tracking=TRACKING_READY,
    output:
        model=TREE.pretrain("{alpha}", "model.pt"),
        train=TREE.pretrain("{alpha}", "train.json"),
    log:
        LOG_TREE.pretrain("{alpha}.log"),
    params:
        **pretrain_step(lambda wc: wc.alpha, lambda wc: wc.alpha, lambda wc: ()),
    priority: PLAN.step_priority("pretrain_alpha")
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.train {params.args} threads={threads} > {log} 2>&1"


rule pretrain_beta:
    input:
        **PLAN.real_set(),
        tracking=TRACKING_READY,
        parent=TREE.pretrain("{alpha}", "model.pt"),
    output:
        model=TREE.pretrain("{beta}_from_{alpha}", "model.pt"),
        train=TREE.pretrain("{beta}_from_{alpha}", "train.json"),
    log:
        LOG_TREE.pretrain("{beta}_from_{alpha}.log"),
    params:
        **pretrain_step(lambda wc: f"{wc.beta}_from_{wc.alpha}", lambda wc: wc.beta, lambda wc: (),
                        **{"pretrain.init_model": lambda i: i.parent}),
    priority: PLAN.step_priority("pretrain_beta")
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.train {params.args} threads={threads} > {log} 2>&1"


rule pretrain_resolution:
    """The final recipe continued at a higher resolution (the scale's `resolution_tiers`; seed 002, 2.4 and 4:
    the 14 models and the ablations at 128x128, the chosen recipe then at 256x256 and 512x512): the previous tier's
    weights at the new image and feature-map size, the final recipe's strategy from the parent's last iteration."""
    input:
        **PLAN.real_set(),
        tracking=TRACKING_READY,
        parent=lambda wc: TREE.pretrain(PLAN.tier(wc.tier).parent, "model.pt"),
    output:
        model=TREE.pretrain("{tier}", "model.pt"),
        train=TREE.pretrain("{tier}", "train.json"),
    log:
        LOG_TREE.pretrain("{tier}.log"),
    params:
        **pretrain_step(lambda wc: wc.tier, lambda wc: PLAN.final_strategy(),
                        lambda wc: PLAN.tier(wc.tier).overrides(),
                        **{"pretrain.init_model": lambda i: i.parent}),
    priority: PLAN.step_priority("pretrain_resolution")
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.train {params.args} threads={threads} > {log} 2>&1"


rule renderer_run:
    input:
        **PLAN.real_set(),
        tracking=TRACKING_READY,
    output:
        model=TREE.pretrain("renderer_{renderer}", "model.pt"),
        train=TREE.pretrain("renderer_{renderer}", "train.json"),
    log:
        LOG_TREE.pretrain("renderer_{renderer}.log"),
    params:
        **pretrain_step(lambda wc: f"renderer_{wc.renderer}", lambda wc: "alpha1",
                        lambda wc: ("experiment=renderer", f"model.renderer={wc.renderer}")),
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.train {params.args} threads={threads} > {log} 2>&1"


rule evaluate_pretrained:
    """A pretrained model on held-out head-model renders beside its trivial baselines (mean colour, nearest
    training sample); its own step, so a new metric re-scores without retraining."""
    input:
        model=TREE.pretrain("{model}", "model.pt"),
        **PLAN.real_set(),
        tracking=TRACKING_READY,
    output:
        report=TREE.pretrain("{model}", "eval.json"),
        samples=report(TREE.pretrain("{model}", "eval_samples.png"), caption="../report/pretrain.rst",
                       category="Pretraining", subcategory="{model}"),
    log:
        LOG_TREE.pretrain("{model}_eval.log"),
    params:
        **step_params("avatarlab.pretrain.evaluate", values=lambda wc, input, output: {
            "evaluate.model": input.model, "evaluate.out": output.report,
            "evaluate.real_subject_dir": str(Path(input.fit).parent)},
            run_dir=lambda wc: TREE.pretrain(wc.model, ".hydra", "eval")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.evaluate {params.args} threads={threads} > {log} 2>&1"


rule renderer_experiment:
    input:
        runs=expand(TREE.pretrain("renderer_{renderer}", "train.json"), renderer=PLAN.renderers),
        evals=expand(TREE.pretrain("renderer_{renderer}", "eval.json"), renderer=PLAN.renderers),
    output:
        report=TREE.report("renderer_experiment.json"),
        figure=report(TREE.report("renderer_experiment.png"), caption="../report/renderer_experiment.rst",
                      category="Pretraining"),
    log:
        LOG_TREE.report("renderer_experiment.log"),
    params:
        code=STEPS.code("avatarlab.pretrain.renderer_experiment"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.renderer_experiment {input.runs:q} --out {output.report:q}"
        " --figure {output.figure:q} > {log} 2>&1"


rule pretrain_all:
    input:
        PLAN.pretrain_outputs(),


rule control_figure:
    """Pretrained models on held-out frames with one control swept (figs. 27, 29-32), each synthesis row under the
    head model's render of the same parameters, scored beside trivial predictors (control_figures in
    workflow/config.yaml)."""
    input:
        models=lambda wc: [TREE.pretrain(m, "model.pt") for m in PLAN.control_figures[wc.figure]["models"]],
        fits=[TREE.subject(s, "fit_rgb.npz") for s in PLAN.shared_videos],
        masks=[TREE.subject(s, "masks.npz") for s in PLAN.shared_videos],
    output:
        report=TREE.controls("{figure}.json"),
        grid=report(TREE.controls("{figure}.png"), caption="../report/pretrain.rst",
                    category="Pretraining", subcategory="controls"),
    log:
        LOG_TREE.pretrain("controls_{figure}.log"),
    wildcard_constraints:
        figure=control_figure_names(),
    params:
        **step_params("avatarlab.pretrain.controls", values=lambda wc, input, output: {
            "controls.models": list(input.models), "controls.subject_dirs": [str(Path(f).parent) for f in input.fits],
            "controls.control": PLAN.control_figures[wc.figure]["control"], "controls.out": output.grid},
            run_dir=lambda wc: TREE.controls(".hydra", wc.figure)),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.controls {params.args} threads={threads} > {log} 2>&1"
