# Pretraining of the parametric head model: the real image set, 2 alpha + 12 beta models, the renderer experiment.


rule init_tracking:
    output:
        TRACKING_READY,
    log:
        "logs/init_tracking.log",
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.tracking init results {output} > {log} 2>&1"


rule synthesize_portraits:
    input:
        code=module_sources("avatarlab.data.portraits"),
    output:
        images=directory(f"{RESULTS}/subjects/{{subject}}/input/images"),
        truth=f"{RESULTS}/subjects/{{subject}}/input/portraits_truth.npz",
    log:
        f"{LOGS}/subjects/{{subject}}/portraits.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "render", "subject", modules=("avatarlab.data.portraits",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/portraits"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.data.portraits {params.hydra} threads={threads} subject.name={wildcards.subject}"
        " 'subject.images_out={output.images}' 'subject.truth_out={output.truth}' > {log} 2>&1"


rule pretrain_alpha:
    input:
        **PRETRAIN_INPUTS,
    output:
        model=f"{RESULTS}/pretrain/{{alpha}}/model.pt",
        metrics=f"{RESULTS}/pretrain/{{alpha}}/metrics.json",
        samples=report(f"{RESULTS}/pretrain/{{alpha}}/samples.png", caption="../report/pretrain.rst",
                       category="Pretraining", subcategory="{alpha}"),
    log:
        f"{LOGS}/pretrain/{{alpha}}.log",
    params:
        settings=lambda wc: settings(*TRAIN_SETTINGS, strategy=wc.alpha, modules=("avatarlab.train.pretrain",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/pretrain/{wc.alpha}/.hydra"),
        run=lambda wc: pretrain_args(wc, wc.alpha, wc.alpha, f"{RESULTS}/pretrain/{wc.alpha}"),
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.train.pretrain {params.hydra} threads={threads} {params.run} > {log} 2>&1"


rule pretrain_beta:
    input:
        **PRETRAIN_INPUTS,
        parent=f"{RESULTS}/pretrain/{{alpha}}/model.pt",
    output:
        model=f"{RESULTS}/pretrain/{{beta}}_from_{{alpha}}/model.pt",
        metrics=f"{RESULTS}/pretrain/{{beta}}_from_{{alpha}}/metrics.json",
        samples=f"{RESULTS}/pretrain/{{beta}}_from_{{alpha}}/samples.png",
    log:
        f"{LOGS}/pretrain/{{beta}}_from_{{alpha}}.log",
    params:
        settings=lambda wc: settings(*TRAIN_SETTINGS, strategy=wc.beta, modules=("avatarlab.train.pretrain",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/pretrain/{wc.beta}_from_{wc.alpha}/.hydra"),
        run=lambda wc, input: pretrain_args(wc, f"{wc.beta}_from_{wc.alpha}", wc.beta,
                                            f"{RESULTS}/pretrain/{wc.beta}_from_{wc.alpha}",
                                            [f"pretrain.init_model={input.parent}"]),
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.train.pretrain {params.hydra} threads={threads} {params.run} > {log} 2>&1"


rule renderer_run:
    input:
        **PRETRAIN_INPUTS,
    output:
        metrics=f"{RESULTS}/pretrain/renderer_{{renderer}}/metrics.json",
    log:
        f"{LOGS}/pretrain/renderer_{{renderer}}.log",
    params:
        settings=lambda wc: settings(*TRAIN_SETTINGS, strategy="alpha1", modules=("avatarlab.train.pretrain",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/pretrain/renderer_{wc.renderer}/.hydra"),
        run=lambda wc: pretrain_args(wc, f"renderer_{wc.renderer}", "alpha1", f"{RESULTS}/pretrain/renderer_{wc.renderer}",
                                     [f"pretrain.renderer={wc.renderer}",
                                      f"pretrain.iterations={scale_value('renderer_experiment_iterations')}",
                                      f"scale.pretrain_image_size={scale_value('renderer_experiment_image_size')}",
                                      f"scale.pretrain_feature_size={scale_value('renderer_experiment_feature_size')}"]),
    threads: step_threads("train")
    resources:
        **step_resources("train"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.train.pretrain {params.hydra} threads={threads} {params.run} > {log} 2>&1"


rule renderer_experiment:
    input:
        runs=expand(f"{RESULTS}/pretrain/renderer_{{renderer}}/metrics.json", renderer=RENDERERS),
        code=module_sources("avatarlab.evaluate.renderer_experiment"),
    output:
        report=f"{RESULTS}/report/renderer_experiment.json",
        figure=report(f"{RESULTS}/report/renderer_experiment.png", caption="../report/renderer_experiment.rst",
                      category="Pretraining"),
    log:
        f"{LOGS}/report/renderer_experiment.log",
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.evaluate.renderer_experiment {input.runs} --out {output.report} --figure {output.figure}"
        " > {log} 2>&1"


rule pretrain_all:
    input:
        pretrain_outputs(),
