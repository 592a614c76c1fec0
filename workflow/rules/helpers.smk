# Helpers the rule files share or use to build their params (Snakemake's lint keeps functions out of rule files).
# (preprocess.smk)
def subject_step(module, name, **values):
    """The params of a per-subject preprocessing step: the subject's own values plus the rule's (a value may be a
    function of the job's input and output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject),
        **{k: v(input, output) if callable(v) else v for k, v in values.items()}},
        run_dir=lambda wc: TREE.subject(wc.subject, ".hydra", name))


# (pretrain.smk)
def real_set(name=None):
    """The preprocessed real image set that pretraining reads."""
    name = name or PLAN.real_images["name"]
    return {"fit": TREE.subject(name, "fit_rgb.npz"), "masks": TREE.subject(name, "masks.npz"),
            "frames": TREE.subject(name, "frames.json")}


# (pretrain.smk)
def pretrain_step(name, strategy, extra, **values):
    """The params of a pretraining run: name(wc) and strategy(wc) choose the model, extra(wc) more config choices."""
    def fixed(wc, input, output):
        return {"pretrain.name": name(wc), "pretrain.out_dir": str(Path(output.model).parent),
                "pretrain.real_subject_dir": str(Path(input.fit).parent), **{k: v(input) for k, v in values.items()}}

    return step_params("avatarlab.train.pretrain", extra=lambda wc: (f"strategy={strategy(wc)}", *extra(wc)),
                       values=fixed, run_dir=lambda wc: TREE.pretrain(name(wc), ".hydra"))


# (avatar.smk)
def avatar_key(wc):
    """The key (subject, recipe, init, frames variant, seed) of the avatar folder a job's wildcards name."""
    return AvatarKey.parse(wc.subject, wc.recipe, wc.avatar)


# (avatar.smk)
def interpolated_input(key):
    """Variant (c) trains on the interpolated frames too."""
    return [TREE.subject(key.subject, "interpolated.npz")] if key.variant == "c" else []


# (avatar.smk)
def finetune_choices(key):
    """The config-group choices of a fine-tuning: its recipe and, for seed k > 0, the seed."""
    return (f"finetune={key.recipe}",) + ((f"seed={key.seed}",) if key.seed else ())


# (avatar.smk)
def app_step(module, name, **values):
    """The params of an application of a subject's final avatar (a value may be a function of wc, input, output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject), "apps.avatar": input.avatar, "apps.subject_dir": PLAN.subject_dir(wc.subject),
        **{k: v(wc, input, output) for k, v in values.items()}},
        run_dir=lambda wc: TREE.app(wc.subject, ".hydra", name))


# (speech.smk)
def speech_audio():
    """The audio to animate: `speech_wav` (a path) if set, else `speech_text` spoken by espeak-ng."""
    if config.get("speech_wav"):
        return {"speech.wav": config["speech_wav"]}
    return {"speech.say": config.get("speech_text", "bin blue at f two now")}


# (pretrain.smk)
def control_figure_names():
    """A wildcard constraint: the figures of control_figures."""
    return alternation(PLAN.control_figures)


# (sweeps.smk)
def sweep_names(step):
    """A wildcard constraint: the sweeps of one kind of step."""
    return alternation(n for n, s in PLAN.sweeps.items() if s.step == step)


# (sweeps.smk)
def sweep_avatar(wc):
    """The avatar a fine-tuning sweep's points vary (its subject, recipe and initialisation)."""
    sweep = PLAN.sweeps[wc.sweep]
    return AvatarKey(sweep.subject, sweep.recipe, sweep.init)


# (sweeps.smk)
def sweep_tags(wc):
    """The MLflow tags of a sweep's point (values, not settings: a new tag reruns nothing)."""
    point = PLAN.sweep_point(wc.sweep, wc.point)
    return {"tracking.sweep": wc.sweep, "tracking.point": wc.point, "tracking.point_overrides": " ".join(point.overrides)}
