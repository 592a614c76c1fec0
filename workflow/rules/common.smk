# Shared helpers: paths, config plumbing and the list of final outputs.
from pathlib import Path

REPO = Path(workflow.basedir)
SCALE = config["scale"]
HEAD_MODEL = config["head_model"]
RESULTS = f"results/{SCALE}"
LOGS = f"logs/{SCALE}"


def conf_files(*extra):
    """The Hydra config files a step reads: declared as inputs so a config change reruns what depends on it."""
    files = ["config.yaml", f"scale/{SCALE}.yaml", f"head_model/{HEAD_MODEL}.yaml", *extra]
    return [str(REPO / "conf" / f) for f in files]


def source_files(*packages):
    """The Python sources a step runs (Snakemake's code trigger covers only the rule's own text)."""
    src = REPO / "src" / "avatarlab"
    files = [src / "config.py", src / "io.py"]
    for package in packages:
        files += sorted((src / package).rglob("*.py"))
    return [str(f) for f in files]


def hydra_args(run_dir):
    """Common Hydra overrides for a step: scale, head model, extra overrides, and its run directory."""
    args = [f"scale={SCALE}", f"head_model={HEAD_MODEL}", *config.get("hydra_overrides", []),
            f"hydra.run.dir={run_dir}"]
    return " ".join(f"'{a}'" for a in args)


SUBJECTS = config.get("subjects", {})
REAL_IMAGES = config["real_images"]
ALL_SUBJECTS = {**SUBJECTS, REAL_IMAGES["name"]: REAL_IMAGES}
SYNTHETIC = [name for name, s in SUBJECTS.items() if s["source"] == "synthetic"]
IMAGE_SETS = [name for name, s in ALL_SUBJECTS.items() if s["source"] in ("portraits", "images")]
ALPHAS, BETAS, RENDERERS = config["alphas"], config["betas"], config["renderers"]
PRETRAINED = ALPHAS + [f"{b}_from_{a}" for b in BETAS for a in ALPHAS]
TRACKING_READY = "results/mlflow.ready"


wildcard_constraints:
    subject="|".join(ALL_SUBJECTS),
    alpha="|".join(ALPHAS),
    beta="|".join(BETAS),
    renderer="|".join(RENDERERS),


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


def get_final_output():
    outputs = [
        f"{RESULTS}/headmodel/render_grid.png",
        f"{RESULTS}/headmodel/dlib_check.json",
    ]
    for subject in SUBJECTS:
        outputs += [f"{subject_dir(subject)}/fit_rgb.json", f"{subject_dir(subject)}/interp.json"]
    for subject in SYNTHETIC:
        outputs += [f"{subject_dir(subject)}/fit_rgbd.json"]
    outputs += pretrain_outputs()
    return outputs


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
    conf=conf_files(*[f"strategy/{s}.yaml" for s in ALPHAS + BETAS]),
    code=source_files("train", "model", "data", "headmodel", "render") + [str(REPO / "src/avatarlab/tracking.py")],
)


def pretrain_args(wc, name, strategy, out_dir, extra=()):
    """Hydra overrides of one pretraining run."""
    args = [f"strategy={strategy}", f"pretrain.name={name}", f"pretrain.out_dir={out_dir}",
            f"pretrain.real_subject_dir={subject_dir(REAL_IMAGES['name'])}", *extra]
    return " ".join(f"'{a}'" for a in args)
