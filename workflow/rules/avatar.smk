# Per-subject avatars (fine-tuning from each pretrained model, interpolation variants) and their applications.


rule finetune_avatar:
    input:
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        masks=f"{RESULTS}/subjects/{{subject}}/masks.npz",
        model=f"{RESULTS}/pretrain/{{init}}/model.pt",
        tracking=TRACKING_READY,
        code=module_sources("avatarlab.train.finetune"),
    output:
        model=f"{RESULTS}/avatars/{{subject}}/{{init}}/model.pt",
        metrics=f"{RESULTS}/avatars/{{subject}}/{{init}}/metrics.json",
        frames=report(f"{RESULTS}/avatars/{{subject}}/{{init}}/test_frames.png", caption="../report/avatar.rst",
                      category="Avatars", subcategory="{subject}"),
    log:
        f"{LOGS}/avatars/{{subject}}/{{init}}.log",
    params:
        settings=lambda wc: settings("finetune", "preprocess", *TRAIN_SETTINGS, modules=("avatarlab.train.finetune",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/avatars/{wc.subject}/{wc.init}/.hydra"),
        subject=subject_args,
        out_dir=lambda wc: f"{RESULTS}/avatars/{wc.subject}/{wc.init}",
    threads: step_threads("finetune")
    resources:
        **step_resources("finetune"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.train.finetune {params.hydra} threads={threads} {params.subject}"
        " 'finetune.init_model={input.model}' 'finetune.init_name={wildcards.init}'"
        " 'finetune.out_dir={params.out_dir}' > {log} 2>&1"


rule finetune_interp_variant:
    """The interpolation experiment's avatars: (b) every second training frame dropped, (c) (b) + the dropped
    frames re-created by the frame interpolator. Variant (a) is the plain avatar of the same initialisation."""
    input:
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        masks=f"{RESULTS}/subjects/{{subject}}/masks.npz",
        interpolated=f"{RESULTS}/subjects/{{subject}}/interpolated.npz",
        model=f"{RESULTS}/pretrain/{{init}}/model.pt",
        tracking=TRACKING_READY,
        code=module_sources("avatarlab.train.finetune"),
    output:
        model=f"{RESULTS}/avatars/{{subject}}/{{init}}_frames{{variant}}/model.pt",
        metrics=f"{RESULTS}/avatars/{{subject}}/{{init}}_frames{{variant}}/metrics.json",
        frames=f"{RESULTS}/avatars/{{subject}}/{{init}}_frames{{variant}}/test_frames.png",
    log:
        f"{LOGS}/avatars/{{subject}}/{{init}}_frames{{variant}}.log",
    params:
        settings=lambda wc: settings("finetune", "preprocess", *TRAIN_SETTINGS, modules=("avatarlab.train.finetune",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/avatars/{wc.subject}/{wc.init}_frames{wc.variant}/.hydra"),
        subject=subject_args,
        out_dir=lambda wc: f"{RESULTS}/avatars/{wc.subject}/{wc.init}_frames{wc.variant}",
    threads: step_threads("finetune")
    resources:
        **step_resources("finetune"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.train.finetune {params.hydra} threads={threads} {params.subject}"
        " 'finetune.init_model={input.model}' 'finetune.init_name={wildcards.init}'"
        " 'finetune.frames_variant={wildcards.variant}' 'finetune.interpolated={input.interpolated}'"
        " 'finetune.out_dir={params.out_dir}' > {log} 2>&1"


rule novel_views:
    input:
        avatar=lambda wc: final_avatar(wc.subject),
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        code=module_sources("avatarlab.apps.novel_views"),
    output:
        grid=report(f"{RESULTS}/apps/{{subject}}/novel_views.png", caption="../report/novel_views.rst",
                    category="Applications", subcategory="{subject}"),
        meta=f"{RESULTS}/apps/{{subject}}/novel_views.json",
    log:
        f"{LOGS}/apps/{{subject}}/novel_views.log",
    params:
        settings=lambda wc: settings("apps", modules=("avatarlab.apps.novel_views",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/apps/{wc.subject}/.hydra/novel_views"),
        subject=subject_args,
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.apps.novel_views {params.hydra} threads={threads} {params.subject}"
        " 'apps.avatar={input.avatar}' 'apps.out={output.grid}' > {log} 2>&1"


rule reenact:
    input:
        avatar=lambda wc: final_avatar(wc.subject),
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        source=f"{RESULTS}/subjects/{{source}}/fit_rgb.npz",
        code=module_sources("avatarlab.apps.reenact"),
    output:
        video=report(f"{RESULTS}/apps/{{subject}}/reenact_{{source}}.mp4", caption="../report/reenact.rst",
                     category="Applications", subcategory="{subject}"),
        frames=f"{RESULTS}/apps/{{subject}}/reenact_{{source}}.png",
        meta=f"{RESULTS}/apps/{{subject}}/reenact_{{source}}.json",
    log:
        f"{LOGS}/apps/{{subject}}/reenact_{{source}}.log",
    params:
        settings=lambda wc: settings("apps", modules=("avatarlab.apps.reenact",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/apps/{wc.subject}/.hydra/reenact_{wc.source}"),
        subject=subject_args,
        source_dir=lambda wc: subject_dir(wc.source),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.apps.reenact {params.hydra} threads={threads} {params.subject}"
        " 'apps.avatar={input.avatar}' 'apps.source_dir={params.source_dir}' 'apps.out={output.video}' > {log} 2>&1"


rule telepresence:
    input:
        avatar=lambda wc: final_avatar(wc.subject),
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        code=module_sources("avatarlab.apps.telepresence"),
    output:
        report=f"{RESULTS}/apps/{{subject}}/telepresence.json",
    log:
        f"{LOGS}/apps/{{subject}}/telepresence.log",
    params:
        settings=lambda wc: settings("apps", modules=("avatarlab.apps.telepresence",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/apps/{wc.subject}/.hydra/telepresence"),
        subject=subject_args,
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.apps.telepresence {params.hydra} threads={threads} {params.subject}"
        " 'apps.avatar={input.avatar}' 'apps.out={output.report}' > {log} 2>&1"


rule avatars_all:
    input:
        avatar_outputs(),
