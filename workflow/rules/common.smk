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


def get_final_output():
    return [
        f"{RESULTS}/headmodel/render_grid.png",
        f"{RESULTS}/headmodel/dlib_check.json",
    ]
