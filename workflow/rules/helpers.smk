# Helpers the rule files share or use to build their params (Snakemake's lint keeps functions out of rule files).
# (preprocess.smk)
def subject_step(module, name, **values):
    """The params of a per-subject preprocessing step: the subject's own values plus the rule's (a value may be a
    function of the job's input and output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject),
        **{k: v(input, output) if callable(v) else v for k, v in values.items()}},
        run_dir=lambda wc: f"{RESULTS}/subjects/{wc.subject}/.hydra/{name}")


# (pretrain.smk)
def real_set(name=None):
    """The preprocessed real image set that pretraining reads."""
    folder = PLAN.subject_dir(name or PLAN.real_images["name"])
    return {"fit": f"{folder}/fit_rgb.npz", "masks": f"{folder}/masks.npz", "frames": f"{folder}/frames.json"}


# (pretrain.smk)
def pretrain_step(name, strategy, extra, **values):
    """The params of a pretraining run: name(wc) and strategy(wc) choose the model, extra(wc) more config choices."""
    def fixed(wc, input, output):
        return {"pretrain.name": name(wc), "pretrain.out_dir": str(Path(output.model).parent),
                "pretrain.real_subject_dir": str(Path(input.fit).parent), **{k: v(input) for k, v in values.items()}}

    return step_params("avatarlab.train.pretrain", extra=lambda wc: (f"strategy={strategy(wc)}", *extra(wc)),
                       values=fixed, run_dir=lambda wc: f"{RESULTS}/pretrain/{name(wc)}/.hydra")


# (avatar.smk)
def finetune_values(subject, init, model, variant="a"):
    """The values naming an avatar: its subject, initialisation, folder (that of its model.pt) and frames variant."""
    return {**PLAN.subject_values(subject), "finetune.subject": subject, "finetune.subject_dir": PLAN.subject_dir(subject),
            "finetune.init_name": init, "finetune.test_clips": PLAN.test_clips(subject),
            "finetune.frames_variant": variant, "finetune.out_dir": str(Path(model).parent)}


# (avatar.smk)
def avatar_variant(wc):
    """init, frames variant and seed of an avatar folder name (<init>, <init>_frames<b|c> or <init>_seed<k>)."""
    name, seed = wc.avatar, 0
    if "_seed" in name:
        name, seed = name.rsplit("_seed", 1)[0], int(name.rsplit("_seed", 1)[1])
    return (name[:-8], name[-1], seed) if name[-8:-1] == "_frames" else (name, "a", seed)


# (avatar.smk)
def app_step(module, name, **values):
    """The params of an application of a subject's final avatar (a value may be a function of wc, input, output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject), "apps.avatar": input.avatar, "apps.subject_dir": PLAN.subject_dir(wc.subject),
        **{k: v(wc, input, output) for k, v in values.items()}},
        run_dir=lambda wc: f"{RESULTS}/apps/{wc.subject}/.hydra/{name}")


# (speech.smk)
def speech_audio():
    """The audio to animate: `speech_wav` (a path) if set, else `speech_text` spoken by espeak-ng."""
    if config.get("speech_wav"):
        return {"speech.wav": config["speech_wav"]}
    return {"speech.say": config.get("speech_text", "bin blue at f two now")}


# (pretrain.smk)
def control_figure_names():
    """A wildcard constraint: the figures of control_figures (never empty: an empty alternation would match '')."""
    import re

    return "|".join(re.escape(n) for n in PLAN.control_figures) or "no-control-figure"


# (sweeps.smk)
def sweep_names(step):
    """A wildcard constraint: the sweeps of one kind of step (never empty: an empty alternation would match '')."""
    import re

    names = [re.escape(n) for n, s in PLAN.sweeps.items() if s.step == step]
    return "|".join(names) or "no-sweep-of-this-kind"


# (sweeps.smk)
def sweep_tags(wc):
    """The MLflow tags of a sweep's point (values, not settings: a new tag reruns nothing)."""
    point = PLAN.sweep_point(wc.sweep, wc.point)
    return {"tracking.sweep": wc.sweep, "tracking.point": wc.point, "tracking.point_overrides": " ".join(point.overrides)}
