"""The report: every table and figure of the reproduction, built only from the files the runs wrote.

Every quality table shows, beside each model's numbers, what trivial predictors score on the same frames (the
evaluation steps' baselines: mean colour / nearest training sample for pretrained models; mean, last and nearest
training frame for avatars) and the model's gain over the best of them; the text under each table names the rows
that do not beat their best baseline. Tables (CSV + Markdown) in `<report>/tables/`: preprocessing, pretraining
(14 models), the renderer experiment, final avatars, alpha1 vs alpha2, beta1-beta6 (figures 39-42), interpolation
(figure 54), table 2 with the dissertation's published rows beside ours, applications, speech. Figures in
`<report>/figures/`: quality vs fine-tuning time (curves, baselines as lines) and vs render time (figures 57-58),
image grids. A number a run could not measure (LPIPS without the backbone, identity without a detected face) is
written "missing", never filled in.
`python -m avatarlab.report.build report.results_dir=results/tiny [report.planned=<JSON list of files>]`: with
`report.planned` (the workflow's report_inputs rule writes it), only the results the workflow planned are read.
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from avatarlab.report.avatar_tables import (
    alpha_paired_table,
    alpha_table,
    beta_table,
    comparison_table,
    face_table,
    final_avatar_table,
    fit_table,
    interp_table,
    same_recording_table,
    sharpness_table,
    stage2_table,
)
from avatarlab.report.claims import claims_table
from avatarlab.report.figures import copy_figure, quality_figures
from avatarlab.report.model_tables import (
    applications_table,
    controls_table,
    preprocessing_table,
    pretraining_table,
    renderer_table,
)
from avatarlab.report.published import PUBLISHED_TABLE2, SUBSTITUTIONS, substitutions_table  # noqa: F401
from avatarlab.report.runs import load_avatars
from avatarlab.report.speech_tables import speech_table, speech_timing_table
from avatarlab.report.table import MISSING, Table, fmt  # noqa: F401 (the report's API)
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path
from avatarlab.workflow.layout import ResultsTree, read_planned

log = logging.getLogger(__name__)


READS = ('report',)  # the config sections this step reads (runtime/entry.py)


#: what the report step writes into its folder (the folder also holds other steps' files: the renderer experiment)
REPORT_PARTS = ("tables", "figures", "README.md", "summary.json")


def build(results: ResultsTree | Path, out: Path, final: str, scale: str) -> dict:
    """Writes the report of `results` (a tree, or its folder: every finished result in it) into a staging folder
    beside `out`, then moves each part into place (summary.json last): an interrupted report leaves the previous one
    whole."""
    tree = results if isinstance(results, ResultsTree) else ResultsTree(Path(results))
    staging = out.parent / f".{out.name}.staging"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    summary = write_report(tree, staging, final, scale)
    out.mkdir(parents=True, exist_ok=True)
    for part in REPORT_PARTS:
        new, old = staging / part, out / part
        if new.is_dir():
            retired = out / f".{part}.old"
            shutil.rmtree(retired, ignore_errors=True)
            if old.exists():
                old.rename(retired)
            new.rename(old)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            new.replace(old)
    shutil.rmtree(staging, ignore_errors=True)
    return summary


def write_report(tree: ResultsTree, out: Path, final: str, scale: str) -> dict:
    tables_dir, figures_dir = out / "tables", out / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    avatars = load_avatars(tree)
    finals, final_baselines = final_avatar_table(avatars, final)
    tables = [preprocessing_table(tree), pretraining_table(tree), controls_table(tree),
              renderer_table(tree), finals, final_baselines, sharpness_table(avatars, final),
              face_table(avatars, final), fit_table(avatars, final), same_recording_table(avatars, final),
              alpha_table(avatars), alpha_paired_table(avatars), beta_table(avatars),
              stage2_table(avatars), interp_table(avatars, final),
              comparison_table(avatars, final, scale), claims_table(tree, avatars, final, scale),
              applications_table(tree), speech_table(tree, scale), speech_timing_table(tree),
              substitutions_table()]
    for table in tables:
        table.write(tables_dir)
    figures = quality_figures(avatars, final, figures_dir) if avatars else []
    for a in avatars:
        if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a" and a["seed"] == 0:
            figures.append(copy_figure(a["dir"] / "test_frames.png", figures_dir / f"test_frames_{a['subject']}.png"))
    for path in tree.find("apps", "*/*.png"):
        figures.append(copy_figure(path, figures_dir / f"{path.parent.name}_{path.name}"))
    for path in tree.find("speech", "speak_*.png"):
        figures.append(copy_figure(path, figures_dir / path.name))
    for name in ("alpha1", "alpha2", final):
        figures += [copy_figure(p, figures_dir / f"pretrained_{name}_held_out.png")
                    for p in tree.find("pretrain", f"{name}/eval_samples.png")]
    for path in tree.find("controls", "*.png"):
        figures.append(copy_figure(path, figures_dir / f"pretrained_controls_{path.name}"))
    figures += [copy_figure(p, figures_dir / "head_model_sweeps.png") for p in tree.find("headmodel", "render_grid.png")]
    figures += [copy_figure(p, figures_dir / "renderer_experiment.png")
                for p in tree.find("report", "renderer_experiment.png")]
    figures = [f for f in figures if f is not None]
    lines = [f"# avatarlab report - scale `{scale}`", "",
             "Every number below was read from a file a workflow step wrote (see `results/` and the MLflow store); "
             "each quality figure stands beside what trivial predictors score on the same frames, and the text under "
             "each table names the rows that do not beat their best baseline. 'missing' means the run could not "
             "measure it (e.g. LPIPS-VGG without its backbone weights).", ""]
    lines += [t.markdown() for t in tables]
    lines += ["## Figures", ""] + [f"![{f.stem}](figures/{f.name})" for f in figures]
    with atomic_path(out / "README.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    summary = {"scale": scale, "final_recipe": final, "avatars": len(avatars), "tables": [t.name for t in tables],
               "figures": [f.name for f in figures],
               "rows": {t.name: len(t.rows) for t in tables}}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return summary


@entry_point(READS)
def main(cfg, device) -> None:
    rep = cfg.report
    tree = ResultsTree(Path(rep.results_dir), read_planned(rep.get("planned")))
    summary = build(tree, Path(rep.out_dir), str(rep.final_recipe), cfg.report.scale)
    log.info("report: %d avatars, tables %s, %d figures -> %s", summary["avatars"], summary["rows"],
             len(summary["figures"]), rep.out_dir)


if __name__ == "__main__":
    main()
