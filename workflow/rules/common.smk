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
SYNTHETIC = [name for name, s in SUBJECTS.items() if s["source"] == "synthetic"]


wildcard_constraints:
    subject="|".join(SUBJECTS) or "none",


def subject_dir(subject):
    return f"{RESULTS}/subjects/{subject}"


def subject_inputs(wildcards):
    """Files the frames of a subject come from: its synthetic video, or the user's paths (globs allowed)."""
    spec = SUBJECTS[wildcards.subject]
    if spec["source"] == "synthetic":
        return [f"{subject_dir(wildcards.subject)}/input/video.mp4"]
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
    return outputs
