# Shared helpers: paths, config plumbing and the list of final outputs.
from pathlib import Path

REPO = Path(workflow.basedir)
SCALE = config["scale"]
HEAD_MODEL = config["head_model"]
RESULTS = f"results/{SCALE}"
# threads of every step, overriding conf/scale/<scale>.yaml `resources.<kind>.cpus` (1 lets --cores 2 run two at once)
THREADS_OVERRIDE = config.get("threads_per_job")
LOGS = f"logs/{SCALE}"


def _compose(extra_overrides=()):
    """The Hydra config this workflow's steps run with (scale, head model, user overrides)."""
    from hydra import compose, initialize_config_dir

    overrides = [f"scale={SCALE}", f"head_model={HEAD_MODEL}", *config.get("hydra_overrides", []), *extra_overrides]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def _scale_config():
    """conf/scale/<scale>.yaml, resolved (with the user's Hydra overrides), composed once per workflow run."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(_compose().scale, resolve=True)


SCALE_CONFIG = _scale_config()
# per kind of step (light, fit, train, finetune, speech) the cpus, memory, runtime and GPUs a step asks for. Locally
# `cpus` is the step's threads; on a cluster the executor (profiles/slurm) turns them all into the job's request.
STEP_RESOURCES = SCALE_CONFIG["resources"]


def scale_value(key):
    """One resolved conf/scale value, for a rule's command line (so that changing it reruns the rule)."""
    return SCALE_CONFIG[key]


def step_threads(kind):
    return int(THREADS_OVERRIDE) if THREADS_OVERRIDE else int(STEP_RESOURCES[kind]["cpus"])


def step_resources(kind):
    """Snakemake resources of a kind of step: mem_mb, runtime (minutes), gpu (count; 0 requests none)."""
    spec = STEP_RESOURCES[kind]
    return {"mem_mb": int(spec["mem_mb"]), "runtime": int(spec["runtime"]), "gpu": int(spec.get("gpu", 0))}


_SETTINGS_CACHE = {}


def settings(*sections, strategy=None, modules=()):
    """The resolved config a step reads, as YAML: its config sections, and of conf/scale only the keys it uses
    (`${scale.key}` in those sections, `scale.key` in the code of `modules` and what they import). Given as a rule's
    `params`, so that a change to exactly these settings reruns the step (Snakemake's params trigger); other edits
    of conf/, a new scale key among them, do not."""
    import re

    from omegaconf import OmegaConf

    key = (sections, strategy, modules)
    if key not in _SETTINGS_CACHE:
        cfg = _compose([f"strategy={strategy}"] if strategy else [])
        picked = {s: OmegaConf.to_container(cfg[s], resolve=False) if OmegaConf.is_config(cfg[s]) else cfg[s]
                  for s in sections}
        used = set(re.findall(r"\$\{scale\.(\w+)\}", OmegaConf.to_yaml(picked)))
        for source in module_sources(*modules):
            used |= set(re.findall(r"\bscale\.(\w+)", Path(source).read_text()))
        scale = OmegaConf.to_container(cfg.scale, resolve=True)
        picked["scale"] = {k: v for k, v in scale.items() if k in used or k == "name"}
        _SETTINGS_CACHE[key] = OmegaConf.to_yaml(picked)
    return _SETTINGS_CACHE[key]


def module_sources(*modules):
    """The avatarlab source files an entry module runs: itself and everything it imports from avatarlab,
    transitively (found by parsing imports, not by importing). Declared as inputs, so editing one of them
    reruns exactly the steps that run it (Snakemake's own code trigger covers only the rule's text)."""
    import ast

    src = REPO / "src"
    seen, todo = set(), list(modules)
    while todo:
        name = todo.pop()
        path = _module_path(src, name)
        if name in seen or not path.is_file():
            continue
        seen.add(name)
        parts = name.split(".")
        package = name if path.name == "__init__.py" else ".".join(parts[:-1])
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                todo += [a.name for a in node.names if a.name.startswith("avatarlab")]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
                if base.startswith("avatarlab"):
                    todo.append(base)
                    todo += [f"{base}.{a.name}" for a in node.names]
        while len(parts) > 1:  # importing a.b.c runs a/__init__ and a/b/__init__
            parts = parts[:-1]
            todo.append(".".join(parts))
    return sorted(str(_module_path(src, name)) for name in seen)


def _module_path(src, name):
    """a.b.c -> src/a/b/c.py, or src/a/b/c/__init__.py for a package."""
    parts = name.split(".")
    source = src.joinpath(*parts[:-1], parts[-1] + ".py")
    return source if source.is_file() else src.joinpath(*parts, "__init__.py")


def hydra_args(run_dir):
    """Common Hydra overrides for a step: scale, head model, extra overrides, and its run directory."""
    args = [f"scale={SCALE}", f"head_model={HEAD_MODEL}", *config.get("hydra_overrides", []),
            f"hydra.run.dir={run_dir}"]
    return " ".join(f"'{a}'" for a in args)


def _available_subjects(subjects):
    """Subjects marked `optional: true` whose path matches no file are left out (with a note), e.g. a real clip that
    exists on one machine only."""
    import glob
    import sys

    kept = {}
    for name, spec in (subjects or {}).items():
        if spec.get("optional") and spec.get("path") and not glob.glob(spec["path"]):
            print(f"avatarlab: optional subject '{name}' skipped: nothing at {spec['path']}", file=sys.stderr)
            continue
        kept[name] = spec
    return kept


SUBJECTS = _available_subjects(config.get("subjects", {}))
REAL_IMAGES = config["real_images"]
ALL_SUBJECTS = {**SUBJECTS, REAL_IMAGES["name"]: REAL_IMAGES}
SYNTHETIC = [name for name, s in SUBJECTS.items() if s["source"] == "synthetic"]
IMAGE_SETS = [name for name, s in ALL_SUBJECTS.items() if s["source"] in ("portraits", "images")]
ALPHAS, BETAS, RENDERERS = config["alphas"], config["betas"], config["renderers"]
PRETRAINED = ALPHAS + [f"{b}_from_{a}" for b in BETAS for a in ALPHAS]
TRACKING_READY = "results/mlflow.ready"
FINAL_RECIPE = config["final_recipe"]
ABLATION_SUBJECTS = [s for s in config.get("ablation_subjects", []) if s in SUBJECTS]
INTERP_SUBJECTS = [s for s in config.get("interp_subjects", []) if s in SUBJECTS]
TRANSFERS = [(t["avatar"], t["source"]) for t in config.get("transfers", [])
             if t["avatar"] in SUBJECTS and t["source"] in SUBJECTS]

# the speech models: seed 000 with / without its regulariser, seed 001's sliding window
SPEECH_MODELS = {"lstm_reg": ["speech.model=lstm", "speech.regularize=true"],
                 "lstm_noreg": ["speech.model=lstm", "speech.regularize=false"],
                 "window": ["speech.model=window"]}


wildcard_constraints:
    subject="|".join(ALL_SUBJECTS),
    alpha="|".join(ALPHAS),
    beta="|".join(BETAS),
    renderer="|".join(RENDERERS),
    init="|".join(PRETRAINED),
    source="|".join(ALL_SUBJECTS),
    variant="b|c",
    speech_model="|".join(SPEECH_MODELS),


def subject_dir(subject):
    return f"{RESULTS}/subjects/{subject}"


def subject_inputs(wildcards):
    """Files the frames of a subject come from: its synthetic video, or the user's paths (globs allowed)."""
    spec = ALL_SUBJECTS[wildcards.subject]
    if spec["source"] == "synthetic":
        return [f"{subject_dir(wildcards.subject)}/input/video.mp4"]
    if spec["source"] == "portraits":
        return [f"{subject_dir(wildcards.subject)}/input/images"]
    import glob

    paths = sorted(glob.glob(spec["path"])) or [spec["path"]]
    return paths


def subject_truth(subject):
    """The ground truth of a synthetic subject (an input of every step that reports errors against it)."""
    return [f"{subject_dir(subject)}/input/truth.npz"] if subject in SYNTHETIC else []


def subject_args(wildcards, input=None):
    """Hydra overrides naming the subject, its folder, its inputs and (if synthetic) its ground truth."""
    sub = wildcards.subject
    args = [f"subject.name={sub}", f"preprocess.subject_dir={subject_dir(sub)}"]
    truth = subject_truth(sub)
    if truth:
        args.append(f"preprocess.truth={truth[0]}")
    if sub in IMAGE_SETS:
        args.append("fit_rgb.mode=images")
    return " ".join(f"'{a}'" for a in args)


def preprocessing_outputs():
    outputs = [f"{RESULTS}/headmodel/render_grid.png", f"{RESULTS}/headmodel/dlib_check.json"]
    for subject in SUBJECTS:
        outputs += [f"{subject_dir(subject)}/fit_rgb.json", f"{subject_dir(subject)}/interp.json"]
    for subject in SYNTHETIC:
        outputs += [f"{subject_dir(subject)}/fit_rgbd.json"]
    return outputs


def avatar_outputs():
    """Every subject's final-recipe avatar and its applications; the 14 initialisations for the ablation subjects;
    the interpolation variants (b, c) for the interpolation subjects."""
    outputs = []
    for subject in SUBJECTS:
        inits = PRETRAINED if subject in ABLATION_SUBJECTS else [FINAL_RECIPE]
        outputs += [f"{RESULTS}/avatars/{subject}/{init}/metrics.json" for init in inits]
        outputs += [f"{RESULTS}/apps/{subject}/novel_views.png", f"{RESULTS}/apps/{subject}/telepresence.json"]
    for subject in INTERP_SUBJECTS:
        outputs += [f"{RESULTS}/avatars/{subject}/{FINAL_RECIPE}_frames{v}/metrics.json" for v in ("b", "c")]
    outputs += [f"{RESULTS}/apps/{avatar}/reenact_{source}.mp4" for avatar, source in TRANSFERS]
    return outputs


def _grid_clips():
    import glob

    return sorted(glob.glob(config["grid_clips"])) if config.get("grid_clips") else []


GRID_CLIPS = _grid_clips()


def speech_outputs():
    """The three speech models (seed 000 with / without its regulariser, seed 001), the speaking avatars, and the
    test on real GRID clips where they exist."""
    outputs = [f"{RESULTS}/speech/{m}/metrics.json" for m in SPEECH_MODELS]
    outputs += [f"{RESULTS}/speech/grid_eval.json"] if GRID_CLIPS else []
    return outputs + [f"{RESULTS}/speech/speak_{s}.mp4" for s in config.get("speech_subjects", []) if s in SUBJECTS]


def get_final_output():
    return (preprocessing_outputs() + pretrain_outputs() + avatar_outputs() + speech_outputs()
            + [f"{RESULTS}/report/README.md"])


def pretrain_outputs():
    return [f"{RESULTS}/pretrain/{name}/metrics.json" for name in PRETRAINED] + [
        f"{RESULTS}/report/renderer_experiment.json"]


def real_set(name):
    """The preprocessed real image set that pretraining reads."""
    folder = subject_dir(name)
    return {"fit": f"{folder}/fit_rgb.npz", "masks": f"{folder}/masks.npz", "frames": f"{folder}/frames.json"}


PRETRAIN_INPUTS = dict(
    **real_set(REAL_IMAGES["name"]),
    tracking=TRACKING_READY,
    code=module_sources("avatarlab.train.pretrain"),
)


TRAIN_SETTINGS = ("seed", "head_model", "render", "model", "synthetic", "pretrain", "tracking")


def pretrain_args(wc, name, strategy, out_dir, extra=()):
    """Hydra overrides of one pretraining run."""
    args = [f"strategy={strategy}", f"pretrain.name={name}", f"pretrain.out_dir={out_dir}",
            f"pretrain.real_subject_dir={subject_dir(REAL_IMAGES['name'])}", *extra]
    return " ".join(f"'{a}'" for a in args)


def final_avatar(subject):
    """The final-recipe avatar of a subject (what the applications and speech use)."""
    return f"{RESULTS}/avatars/{subject}/{FINAL_RECIPE}/model.pt"


def speech_input_args():
    """The audio to animate: `speech_wav` (a path) if set, else `speech_text` spoken by espeak-ng."""
    if config.get("speech_wav"):
        return f"'speech.wav={config['speech_wav']}'"
    return f"'speech.say={config.get('speech_text', 'bin blue at f two now')}'"
