"""`avatarlab <command>`: the platform's front door.

    avatarlab run [TARGET ...] [--scale S] [--cores N] [-- SNAKEMAKE ARGS]   the workflow, quiet console
    avatarlab status [--scale S]            what is done, what would run and why
    avatarlab add-subject NAME PATH [--fps F]   your own video (a file or a glob) as a subject, validated,
                                           kept in avatarlab.subjects.yaml
    avatarlab report [--scale S]            the report and the results card again, and where they are
    avatarlab dashboard [--scale S]         the MLflow dashboard (127.0.0.1)
    avatarlab clean [--scale S] --yes       delete results/<scale> and logs/<scale>
    avatarlab render-demo | dlib-check [hydra overrides]   single steps

The scale: --scale, else the one `make main SCALE=` or `avatarlab run --scale` chose last (.avatarlab-scale), else
tiny. Every command runs in the checkout the package was installed from.
"""
from __future__ import annotations

import argparse
import glob
import re
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
WORKDIR = REPO  # where results/ and logs/ go: the checkout
LOCAL_SUBJECTS = REPO / "avatarlab.subjects.yaml"  # read by the Snakefile from its work folder
STEPS = {
    "render-demo": ("avatarlab.pretrain.head_model_demo", "PNG grid sweeping every head-model parameter"),
    "dlib-check": ("avatarlab.pretrain.dlib_check", "dlib detection rate and NME on renders of the head model"),
}
NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def scale_of(given: str | None) -> str:
    from avatarlab.workflow.steps import SCALE_FILE, chosen_scale

    scale = chosen_scale(given, REPO)
    if given:
        (REPO / SCALE_FILE).write_text(scale + "\n")
    return scale


def snakemake(*args: str, capture: bool = False) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "snakemake"
    return subprocess.run([str(exe), "-s", str(REPO / "Snakefile"), "--directory", str(WORKDIR), *args],
                          capture_output=capture, text=True)


def run(args) -> int:
    scale = scale_of(args.scale)
    extra = list(args.snakemake or [])
    return snakemake(*args.targets, "--cores", str(args.cores), "--logger", "avatarlab", *extra,
                     "--config", f"scale={scale}").returncode


def _flat(tree, prefix: str = "") -> dict:
    if isinstance(tree, dict):
        out = {}
        for key, value in tree.items():
            out.update(_flat(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: tree}


def changed_settings(block: str) -> list[str]:
    """The settings keys (and 'code') whose change a dry run's "Params have changed" reason reports, instead of
    the two resolved configs it prints: e.g. ['fit_rgb.held_out.test_frames: 3 -> 5', 'code']."""
    import ast

    import yaml

    if "Params have changed" not in block:
        return []
    found = re.search(r"before: (.*?) now: (.*?)\s*$", block.split("reason: ", 1)[-1].split("\n    wildcards:")[0],
                      re.S)
    if found is None:
        return []

    def params(text: str) -> list:
        try:
            return list(ast.literal_eval("[" + text.strip() + "]"))
        except (ValueError, SyntaxError):
            return []
    before, now = params(found.group(1)), params(found.group(2))
    digest = re.compile(r"^[0-9a-f]{16}$")
    out = ["code"] if any(isinstance(p, str) and digest.match(p) for p in before + now) else []
    old = next((p for p in before if isinstance(p, str) and ":" in p and not digest.match(p)), None)
    new = next((p for p in now if isinstance(p, str) and ":" in p and not digest.match(p)), None)
    if old is not None and new is not None:
        try:
            a, b = _flat(yaml.safe_load(old)), _flat(yaml.safe_load(new))
        except yaml.YAMLError:
            return out
        for key in sorted(set(a) | set(b)):
            if key not in a:
                out.append(f"{key} (new: {b[key]!r})")
            elif key not in b:
                out.append(f"{key} (gone)")
            elif a[key] != b[key]:
                out.append(f"{key}: {a[key]!r} -> {b[key]!r}")
    return out


def status(args) -> int:
    """Counts of what is done and what would run, per rule, with the reasons Snakemake gives."""
    scale = scale_of(args.scale)
    out = snakemake("-n", "--cores", "1", "--config", f"scale={scale}", capture=True)
    text = out.stdout + out.stderr
    if out.returncode:
        print(text[-3000:], file=sys.stderr)
        return out.returncode
    if "Nothing to be done" in text:
        print(f"scale {scale}: everything is done and up to date (results/{scale}/)")
        return 0
    reasons: dict[str, dict[str, int]] = {}
    for block in text.split("\nrule ")[1:]:
        rule = block.split(":", 1)[0].strip()
        reason = re.search(r"reason: ([^\n;:]+)", block)
        why = reason.group(1).strip() if reason else "?"
        keys = changed_settings(block)
        if keys:
            why += " (" + ", ".join(keys) + ")"
        reasons.setdefault(rule, {}).setdefault(why, 0)
        reasons[rule][why] += 1
    total = sum(sum(r.values()) for r in reasons.values())
    print(f"scale {scale}: {total} steps would run")
    for rule, whys in reasons.items():
        print(f"  {rule:<26} " + "; ".join(f"{n} x {why}" for why, n in whys.items()))
    return 0


def add_subject(args) -> int:
    """Writes the subject into avatarlab.subjects.yaml in the checkout (not committed; the Snakefile merges it into
    `subjects`) after checking it as the workflow would, and prints its targets."""
    import yaml

    from avatarlab.workflow.targets import Plan

    if not NAME.match(args.name):
        print(f"error: subject name {args.name!r}: letters, digits and _ only, starting with a letter", file=sys.stderr)
        return 2
    path = str(Path(args.path).expanduser().resolve()) if not glob.has_magic(args.path) else args.path
    found = sorted(glob.glob(path)) or ([path] if Path(path).exists() else [])
    if not found:
        print(f"error: {args.path}: no such file or folder", file=sys.stderr)
        return 2
    spec = {"source": "images" if Path(found[0]).is_dir() else "video", "path": path}
    if args.fps:
        spec["fps"] = args.fps
    local = yaml.safe_load(LOCAL_SUBJECTS.read_text()) if LOCAL_SUBJECTS.is_file() else None
    local = local or {"subjects": {}}
    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    merged = {**config, "scale": scale_of(args.scale),
              "subjects": {**config["subjects"], **local["subjects"], args.name: spec}}
    try:
        plan = Plan(merged)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    local["subjects"][args.name] = spec
    tmp = LOCAL_SUBJECTS.with_suffix(".tmp")
    tmp.write_text("# your own subjects (avatarlab add-subject); the Snakefile merges them into `subjects`\n"
                   + yaml.safe_dump(local, sort_keys=False))
    tmp.replace(LOCAL_SUBJECTS)
    final = plan.avatar_dir(args.name, "final", plan.final_recipe)
    print(f"subject {args.name}: {len(found)} input(s), written to {LOCAL_SUBJECTS}")
    print("its results (`avatarlab run <target>` makes one, `avatarlab run` everything):")
    for target in (plan.tree.subject(args.name, "fit_rgb.json"), f"{final}/eval.json",
                   plan.tree.app(args.name, "novel_views.png")):
        print(f"  {target}")
    return 0


def report(args) -> int:
    from avatarlab.workflow.layout import ResultsTree, results_root

    scale = scale_of(args.scale)
    tree = ResultsTree(results_root(scale))
    done = snakemake(tree.report("README.md"), "--cores", "1", "--logger", "avatarlab", "--config",
                     f"scale={scale}").returncode
    if done:
        return done
    subprocess.run([sys.executable, "-m", "avatarlab.report.results_card", "--results", tree.root], cwd=REPO)
    html = tree.report("workflow_report.html")
    snakemake("--report", html, "--config", f"scale={scale}", capture=True)
    for path in (tree.report("RESULTS.md"), tree.report("README.md"), html):
        print(f"  {REPO / path}")
    return 0


def dashboard(args) -> int:
    from avatarlab.runtime import dashboard as dash

    return dash.main(["--results", str(REPO / "results"), "--scale", scale_of(args.scale)])


def clean(args) -> int:
    scale = scale_of(args.scale)
    folders = [REPO / "results" / scale, REPO / "logs" / scale]
    if not args.yes:
        print("would delete " + ", ".join(str(f) for f in folders if f.exists()) + " (add --yes)")
        return 1
    for folder in folders:
        shutil.rmtree(folder, ignore_errors=True)
    print(f"deleted results and logs of scale {scale}")
    return 0


#: every command, in the order `avatarlab --help` lists them
COMMANDS = ("run", "status", "add-subject", "report", "dashboard", "clean", *STEPS)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="avatarlab", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", metavar="command")
    commands = {
        "run": (run, "run the workflow (or the targets given) with a quiet console"),
        "status": (status, "what is done, what would run and why"),
        "add-subject": (add_subject, "add your own video or image folder as a subject"),
        "report": (report, "make the report and results card again and print where they are"),
        "dashboard": (dashboard, "the MLflow dashboard on 127.0.0.1"),
        "clean": (clean, "delete the results and logs of a scale"),
    }
    for name, (fn, help_text) in commands.items():
        c = sub.add_parser(name, help=help_text)
        c.set_defaults(fn=fn)
        c.add_argument("--scale", choices=("smoke", "tiny", "paper"), help="remembered for later commands")
        if name == "run":
            c.add_argument("targets", nargs="*", help="result files to make (default: everything)")
            c.add_argument("--cores", type=int, default=2)
            c.add_argument("snakemake", nargs=argparse.REMAINDER, help="after --: more Snakemake arguments")
        if name == "add-subject":
            c.add_argument("name")
            c.add_argument("path", help="a video, a glob of clips, or a folder of images")
            c.add_argument("--fps", type=float, help="frames per second to keep")
        if name == "clean":
            c.add_argument("--yes", action="store_true")
    for name, (_, help_text) in STEPS.items():
        sub.add_parser(name, help=f"{help_text} (Hydra overrides follow)", add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in STEPS:
        module = STEPS[argv[0]][0]
        sys.argv = [module, *argv[1:]]
        runpy.run_module(module, run_name="__main__")
        return 0
    args = parser().parse_args(argv)
    if not getattr(args, "fn", None):
        parser().print_help()
        return 2
    if getattr(args, "snakemake", None) and args.snakemake[0] == "--":
        args.snakemake = args.snakemake[1:]
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
