# Helpers the rule files share or use to build their params (Snakemake's lint keeps functions out of rule files).
# Wiring only; what they decide is the Plan's (src/avatarlab/workflow/targets.py, tested in test_workflow_module).
# (preprocess.smk)
def subject_step(module, name, **values):
    """The params of a per-subject preprocessing step: the subject's own values plus the rule's (a value may be a
    function of the job's input and output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject),
        **{k: v(input, output) if callable(v) else v for k, v in values.items()}},
        run_dir=lambda wc: TREE.subject(wc.subject, ".hydra", name))


# (pretrain.smk)
def pretrain_step(name, strategy, extra, **values):
    """The params of a pretraining run: name(wc) and strategy(wc) choose the model, extra(wc) more config choices."""
    def fixed(wc, input, output):
        return {"pretrain.name": name(wc), "pretrain.out_dir": str(Path(output.model).parent),
                "pretrain.real_subject_dir": str(Path(input.fit).parent), **{k: v(input) for k, v in values.items()}}

    return step_params("avatarlab.pretrain.train", extra=lambda wc: (f"strategy={strategy(wc)}", *extra(wc)),
                       values=fixed, run_dir=lambda wc: TREE.pretrain(name(wc), ".hydra"))


# (avatar.smk)
def avatar_key(wc):
    """The key (subject, recipe, init, frames variant, seed) of the avatar folder a job's wildcards name."""
    return AvatarKey.parse(wc.subject, wc.recipe, wc.avatar)


# (avatar.smk)
def app_step(module, name, **values):
    """The params of an application of a subject's final avatar (a value may be a function of wc, input, output)."""
    return step_params(module, values=lambda wc, input, output: {
        **PLAN.subject_values(wc.subject), "apps.avatar": input.avatar, "apps.subject_dir": PLAN.subject_dir(wc.subject),
        **{k: v(wc, input, output) for k, v in values.items()}},
        run_dir=lambda wc: TREE.app(wc.subject, ".hydra", name))


# (pretrain.smk)
def control_figure_names():
    """A wildcard constraint: the figures of control_figures."""
    return alternation(PLAN.control_figures)


# (sweeps.smk)
def sweep_names(step):
    """A wildcard constraint: the sweeps of one kind of step."""
    return alternation(PLAN.sweep_names(step))
