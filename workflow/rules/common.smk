# Wiring of the rules to the workflow package (src/avatarlab/workflow/, unit-tested): the plan of results and each
# step's settings, code digest and quoted command line. No logic lives here.
import sys
from pathlib import Path

REPO = Path(workflow.basedir)
sys.path.insert(0, str(REPO / "src"))

from snakemake.utils import validate  # noqa: E402

from avatarlab.workflow.steps import Steps, chosen_scale, interpreter_first_on_path  # noqa: E402
from avatarlab.workflow.layout import (  # noqa: E402
    TRACKING_LOG, TRACKING_READY, AvatarKey, ResultsTree, alternation, avatar_folder_pattern, write_planned)
from avatarlab.workflow.targets import Plan  # noqa: E402

interpreter_first_on_path()  # `.venv/bin/snakemake` works without an activated venv
config["scale"] = chosen_scale(config.get("scale"))  # --config scale=..., else the one `make main SCALE=` chose
validate(config, schema="../schemas/config.schema.yaml")  # a wrong key or value stops here, before any job
STEPS = Steps(REPO / "conf", config["scale"], config["head_model"], config.get("hydra_overrides", []))
SCALE = STEPS.compose().scale
PLAN = Plan(config, sweep_dir=REPO / "conf" / "sweep", scale=SCALE)
TREE, LOG_TREE = PLAN.tree, ResultsTree(PLAN.logs)  # every path of the results tree (workflow/layout.py)
LANDING = Path(TREE.report("landing.html"))  # the results card's tables: the HTML report's front page
if LANDING.is_file():
    config["report_landing"] = str(LANDING.resolve())
# per kind of step (light, fit, train, finetune, speech): cpus (= threads locally), mem_mb, runtime, gpu; a cluster
# executor (profiles/slurm) turns them into each job's request. `threads_per_job` overrides the cpus locally.
STEP_RESOURCES = SCALE.resources
THREADS_OVERRIDE = config.get("threads_per_job")


def step_threads(kind):
    return int(THREADS_OVERRIDE) if THREADS_OVERRIDE else int(STEP_RESOURCES[kind].cpus)


def step_resources(kind):
    spec = STEP_RESOURCES[kind]
    return {"mem_mb": int(spec.mem_mb), "runtime": int(spec.runtime), "gpu": int(spec.get("gpu", 0))}


def get_final_output():
    return PLAN.final_outputs()


wildcard_constraints:
    subject="|".join(PLAN.all_subjects),
    source="|".join(PLAN.all_subjects),
    alpha="|".join(PLAN.alphas),
    beta="|".join(PLAN.betas),
    renderer="|".join(PLAN.renderers),
    init="|".join(PLAN.initialisations),
    tier="|".join(t.name for t in PLAN.tiers) or "(?!)",  # (?!): no tier at this scale matches nothing
    recipe="base|final",
    avatar=avatar_folder_pattern(PLAN.initialisations),
    variant="b|c",
    seed="[1-9][0-9]*",
    speech_model="|".join(PLAN.speech_models),


def step_params(module, extra=None, values=None, run_dir=None):
    """A step's Snakemake params. `settings` (the resolved sections it reads) and `code` (the digest of what it runs)
    depend on the wildcards only, so Snakemake records them and reruns the step when either changes; `args` is its
    quoted command line and may name input and output paths (Snakemake does not compare such "derived" params).
    extra(wc): config-group choices (e.g. strategy=beta4); values(wc, input, output): key -> value; run_dir(wc)."""
    variant = extra or (lambda wc: ())
    return {
        "settings": lambda wc: STEPS.settings(module, *variant(wc)),
        "code": STEPS.code(module),
        "args": lambda wc, input, output: STEPS.args(module, *variant(wc),
                                                     values=values(wc, input, output) if values else None,
                                                     run_dir=run_dir(wc) if run_dir else None),
    }
