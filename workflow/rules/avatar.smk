# Per-subject avatars (the final recipe for every subject; base fine-tunes from each pretrained model and the
# interpolation variants for the ablation subjects), their evaluation, and the applications.


rule finetune_avatar:
    """Every avatar. Its folder name is its key (workflow/layout.py): <init> (seed 0, all training frames),
    <init>_seed<k> (another seed: batch order, synthetic samples, offsets; the seed-to-seed spread every comparison
    of avatars is judged against), <init>_frames<b|c> (the interpolation experiment, base recipe: (b) every second
    training frame dropped, (c) (b) + the dropped frames re-created by the frame interpolator)."""
    input:
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
        masks=TREE.subject("{subject}", "masks.npz"),
        interpolated=lambda wc: PLAN.interpolated_input(avatar_key(wc)),
        model=lambda wc: TREE.pretrain(avatar_key(wc).init, "model.pt"),
        tracking=TRACKING_READY,
    output:
        model=TREE.avatar("{subject}", "{recipe}", "{avatar}", "model.pt"),
        train=TREE.avatar("{subject}", "{recipe}", "{avatar}", "train.json"),
    log:
        LOG_TREE.avatar("{subject}", "{recipe}", "{avatar}.log"),
    params:
        **step_params(
            "avatarlab.avatar.finetune", extra=lambda wc: PLAN.finetune_choices(avatar_key(wc)),
            values=lambda wc, input, output: {**PLAN.finetune_values(avatar_key(wc), output.model),
                                              "finetune.init_model": input.model,
                                              **({"finetune.interpolated": input.interpolated[0]}
                                                 if input.interpolated else {})},
            run_dir=lambda wc: TREE.avatar(wc.subject, wc.recipe, wc.avatar, ".hydra")),
    priority: lambda wc: PLAN.step_priority("finetune_avatar", recipe=wc.recipe)
    threads: step_threads("finetune")
    resources:
        **step_resources("finetune"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.finetune {params.args} threads={threads} > {log} 2>&1"


rule evaluate_avatar:
    """An avatar on its test frames beside the mean, last and nearest training frame; its own step, so a new metric
    re-scores without retraining."""
    input:
        model=TREE.avatar("{subject}", "{recipe}", "{avatar}", "model.pt"),
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
        masks=TREE.subject("{subject}", "masks.npz"),
        landmarks=TREE.subject("{subject}", "landmarks.npz"),
        interpolated=lambda wc: PLAN.interpolated_input(avatar_key(wc)),
        tracking=TRACKING_READY,
    output:
        report=TREE.avatar("{subject}", "{recipe}", "{avatar}", "eval.json"),
        frames=report(TREE.avatar("{subject}", "{recipe}", "{avatar}", "test_frames.png"),
                      caption="../report/avatar.rst", category="Avatars", subcategory="{subject}"),
    log:
        LOG_TREE.avatar("{subject}", "{recipe}", "{avatar}_eval.log"),
    params:
        **step_params(
            "avatarlab.avatar.evaluate", extra=lambda wc: (f"finetune={wc.recipe}",),
            values=lambda wc, input, output: {
                **PLAN.finetune_values(avatar_key(wc), input.model),
                "seed": avatar_key(wc).seed, "evaluate.model": input.model, "evaluate.out": output.report,
                **({"finetune.interpolated": input.interpolated[0]} if input.interpolated else {})},
            run_dir=lambda wc: TREE.avatar(wc.subject, wc.recipe, wc.avatar, ".hydra", "eval")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.evaluate {params.args} threads={threads} > {log} 2>&1"


rule novel_views:
    input:
        avatar=lambda wc: PLAN.final_avatar(wc.subject),
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
    output:
        grid=report(TREE.app("{subject}", "novel_views.png"), caption="../report/novel_views.rst",
                    category="Applications", subcategory="{subject}"),
        meta=TREE.app("{subject}", "novel_views.json"),
    log:
        LOG_TREE.app("{subject}", "novel_views.log"),
    params:
        **app_step("avatarlab.avatar.novel_views", "novel_views", **{"apps.out": lambda wc, i, o: o.grid}),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.novel_views {params.args} threads={threads} > {log} 2>&1"


rule reenact:
    input:
        avatar=lambda wc: PLAN.final_avatar(wc.subject),
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
        source=TREE.subject("{source}", "fit_rgb.npz"),
    output:
        video=report(TREE.app("{subject}", "reenact_{source}.mp4"), caption="../report/reenact.rst",
                     category="Applications", subcategory="{subject}"),
        frames=TREE.app("{subject}", "reenact_{source}.png"),
        meta=TREE.app("{subject}", "reenact_{source}.json"),
    log:
        LOG_TREE.app("{subject}", "reenact_{source}.log"),
    params:
        **app_step("avatarlab.avatar.reenact", "reenact", **{
            "apps.out": lambda wc, i, o: o.video, "apps.source_dir": lambda wc, i, o: PLAN.subject_dir(wc.source)}),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.reenact {params.args} threads={threads} > {log} 2>&1"


rule telepresence:
    input:
        avatar=lambda wc: PLAN.final_avatar(wc.subject),
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
    output:
        report=TREE.app("{subject}", "telepresence.json"),
    log:
        LOG_TREE.app("{subject}", "telepresence.log"),
    params:
        **app_step("avatarlab.avatar.telepresence", "telepresence", **{"apps.out": lambda wc, i, o: o.report}),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.avatar.telepresence {params.args} threads={threads} > {log} 2>&1"


rule avatars_all:
    input:
        PLAN.avatar_outputs(),
