"""The results card of one `make main`: where and how the run was made, where its time went, and its headline tables,
each number beside its best trivial baseline and its confidence interval.

    python -m avatarlab.report.results_card --results results/tiny --start results/.main_tiny.start [--log LOG]

Written last by `make main` (after the workflow, before Snakemake's HTML report) to `<results>/report/RESULTS.md`.
Provenance: the commit and whether the tree had uncommitted changes, the start and end time, the machine's CPU model
and the flags that change float arithmetic, the core count, memory, Python, torch and its thread count, Snakemake,
whether the run started from an empty results folder ("fresh") or resumed one, the wall time of `make main` and the
step-time table of its workflow run. The headline tables are the report's own (evaluate/*_tables.py), cut to the
columns that carry the comparison; the full tables stay in `<results>/report/tables/`. A figure that is quoted
anywhere else (README, docs) must be copied from a card: `tests/test_results_card.py` checks the README's.
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

from avatarlab.report.avatar_tables import (
    face_table,
    final_avatar_table,
    fit_table,
    same_recording_table,
    sharpness_table,
)
from avatarlab.report.claims import RULE, claims_table
from avatarlab.report.model_tables import preprocessing_table, pretraining_table
from avatarlab.report.runs import load_avatars
from avatarlab.report.speech_tables import speech_table
from avatarlab.report.table import Headline, Table, read_json
from avatarlab.runtime.errors import ConfigError
from avatarlab.runtime.io import atomic_path
from avatarlab.workflow import step_times
from avatarlab.workflow.layout import ResultsTree, read_planned

ROOT = Path(__file__).resolve().parents[3]
#: CPU flags that decide which float kernels run (and so the last digits of a result)
ARITHMETIC_FLAGS = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_tile", "amx_bf16", "neon", "asimd")


def git(*words: str) -> str | None:
    try:
        out = subprocess.run(["git", *words], cwd=ROOT, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def commit_line() -> str:
    head = git("rev-parse", "HEAD")
    if head is None:
        return "unknown (not a git checkout)"
    status = git("status", "--porcelain", "--untracked-files=no") or ""
    dirty = [line.split(maxsplit=1)[-1] for line in status.splitlines() if line.strip()]
    return f"{head} ({'uncommitted changes in ' + ', '.join(dirty) if dirty else 'clean tree'})"


def cpu() -> tuple[str, list[str]]:
    model, flags = platform.processor() or platform.machine(), []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = [f for f in ARITHMETIC_FLAGS if f in value.split()]
    except OSError:
        pass
    return model, flags


def memory_gib() -> str:
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        return f"{pages * size / 2**30:.0f} GiB"
    except (ValueError, OSError):
        return "unknown"


def duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{seconds / 60:.1f} min"


def provenance(start_file: Path | None, log: Path | None, now: datetime) -> list[tuple[str, str]]:
    import snakemake
    import torch

    model, flags = cpu()
    started, fresh = None, None
    if start_file is not None and start_file.is_file():
        stamp, _, state = start_file.read_text().strip().partition(" ")
        started, fresh = datetime.fromtimestamp(float(stamp), timezone.utc), state
    rows = [("commit", commit_line()),
            ("run", {"fresh": "fresh: the results folder did not exist when `make main` started",
                     "resumed": "RESUMED: the results folder existed when `make main` started; the step times "
                                "below cover this invocation only"}.get(fresh, "unknown: no start record")),
            ("started (UTC)", started.strftime("%Y-%m-%d %H:%M:%S") if started else "unknown"),
            ("finished (UTC)", now.strftime("%Y-%m-%d %H:%M:%S")),
            ("wall time of make main", duration((now - started).total_seconds()) if started else "unknown"),
            ("machine", f"{model}; {os.cpu_count()} cores; {memory_gib()}; flags {' '.join(flags) or 'none listed'}"),
            ("software", f"Python {platform.python_version()}, torch {torch.__version__} "
                         f"({torch.get_num_threads()} threads in this process; each step sets its own), "
                         f"Snakemake {snakemake.__version__}, {platform.system()} {platform.release()}"),
            ("workflow log", str(log) if log else "none found")]
    return rows


def cut(table: Table, columns: list[str], title: str | None = None, note: str | None = None) -> Table:
    """The table as the card shows it: only `columns` (in that order, at most 8), its note kept unless another is
    given, its headline (best row, sentence) and CI columns kept."""
    short = Table(table.name, title or table.title, table.columns, table.note if note is None else note,
                  shown=[c for c in columns if c in table.columns], headline=table.headline,
                  ci_columns=table.ci_columns)
    short.rows = table.rows
    return short


def interpolated(table: Table) -> Table:
    """The preprocessing table's rows of the subjects the interpolation experiment scored."""
    table.rows = [r for r in table.rows if r.get("interp_xvfi_psnr") is not None]
    return table


def headline_tables(results: ResultsTree, final: str, scale: str) -> list[Table]:
    avatars = load_avatars(results)
    finals, _ = final_avatar_table(avatars, final)
    speech = speech_table(results, scale)
    real = Table("speech_real", "Speech on real clips (lip error, % IOD, motion only)", speech.columns,
                 "Against a still mouth on the same frames; gain_iod > 0: the model is better; a gain is one only "
                 "beyond its clip-level 95 % CI.", ci_columns=speech.ci_columns,
                 headline=Headline("gain_iod", ("method", "data"), gain="gain_iod",
                                   gain_ci="clip_gain_ci95"))
    real.rows = [r for r in speech.rows if r.get("source") == "this run" and "real" in str(r.get("data"))]
    claims = claims_table(results, avatars, final, scale)
    claims.note = RULE
    preprocessing = interpolated(preprocessing_table(results))
    preprocessing.headline = Headline("interp_xvfi_psnr", ("subject",), gain="interp_gain_vs_crossfade_db",
                                      gain_ci="interp_gain_vs_crossfade_ci95", baseline=None, each=True,
                                      versus="the cross-fade")
    return [
        cut(pretraining_table(results), ["model", "iterations", "psnr_head", "mean_colour_psnr_head",
                                         "nearest_psnr_head", "gain", "st_lpips", "best_baseline_st_lpips"]),
        cut(finals, ["subject", "seeds", "test_frames", "psnr", "baseline_psnr", "gain", "ssim", "st_lpips"]),
        sharpness_table(avatars, final),
        face_table(avatars, final),
        fit_table(avatars, final),
        same_recording_table(avatars, final),
        cut(preprocessing, ["subject", "interp_xvfi_psnr", "interp_farneback_psnr", "interp_crossfade_psnr",
                            "interp_gain_vs_farneback_db", "interp_gain_vs_crossfade_db"],
            "Frame interpolation on held-out frames (PSNR, dB), beside Farneback flow and the cross-fade",
            "The XVFI-style network and its two baselines on the same held-out frames (those between two frames of "
            "one clip); gains: its mean per-frame PSNR gain over each baseline with the 95 % CI over frames."),
        cut(real, ["method", "data", "motion_error_iod", "baseline_iod", "gain_iod", "wins", "fine_tuning_seeds"]),
        cut(claims, ["claim", "published", "this_run", "noise", "verdict"]),
    ]


LANDING_STYLE = ("<style>.avatarlab table{border-collapse:collapse;margin:.4em 0 1.2em}.avatarlab td,.avatarlab th"
                 "{border:1px solid #ccc;padding:2px 8px;text-align:right;font-size:13px}.avatarlab td:first-child,"
                 ".avatarlab th:first-child{text-align:left}.avatarlab tr.best{background:#eef7ee}.avatarlab p.note,"
                 ".avatarlab p.more{font-size:12px;color:#555;max-width:70em}</style>")


def landing_html(provenance_rows: list[tuple[str, str]], tables: list[Table]) -> str:
    """The HTML report's landing (workflow/report/workflow.rst includes it): the provenance and the headline tables,
    rendered (not a download)."""
    import html

    facts = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in provenance_rows)
    return (LANDING_STYLE + '<div class="avatarlab"><h2>Results card</h2><p>Every number below was written by this '
            "run; each stands beside its best trivial baseline on the same frames and its 95 % CI. The full "
            "tables are in the categories below and in <code>report/tables/</code>.</p>"
            f"<table>{facts}</table>" + "".join(t.html() for t in tables) + "</div>\n")


def write_card(results: Path, final: str, scale: str, start_file: Path | None, log: Path | None,
               now: datetime | None = None) -> Path:
    if not results.is_dir():
        raise ConfigError(f"{results}: no results folder (run the workflow first)")
    now = now or datetime.now(timezone.utc)
    lines = [f"# Results card: scale `{scale}`", "",
             "Every number below was written by this one run of `make main`; each stands beside its best trivial "
             "baseline on the same frames and its 95 % CI. The full tables: `report/tables/`.", "",
             "## Provenance", "", "| | |", "| --- | --- |"]
    facts = provenance(start_file, log, now)
    lines += [f"| {k} | {v} |" for k, v in facts]
    if log is not None:
        try:
            lines += ["", "## Step times", "", step_times.table(step_times.parse_log(log), os.cpu_count() or 1)]
        except ConfigError as err:
            lines += ["", "## Step times", "", f"not read: {err}"]
    planned = ResultsTree(results).report("planned.json")  # the results the workflow planned (report_inputs)
    tree = ResultsTree(results, read_planned(planned) if planned.is_file() else None)
    tables = headline_tables(tree, final, scale)
    lines += ["", "## Headline tables", ""] + [t.markdown() for t in tables]
    out = tree.report("RESULTS.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_path(out.with_name("landing.html")) as tmp:
        tmp.write_text(landing_html(facts, tables))
    return out


NUMBER = re.compile(r"(?<![\w.])[-+]?\d+(?:\.\d+)?")


def numbers_not_in(text: str, card: str) -> list[str]:
    """The numbers quoted in `text` (a README's results section) that the card does not contain as written: a figure
    quoted anywhere must be copied from the one card it names."""
    have = set(NUMBER.findall(card))
    return [n for n in NUMBER.findall(text) if n not in have and n.lstrip("+-") not in have]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="results/<scale>")
    parser.add_argument("--start", type=Path, help="the start record `make main` wrote ('<epoch> fresh|resumed')")
    parser.add_argument("--log", type=Path, help="the workflow run's Snakemake log (default: the newest)")
    parser.add_argument("--final", default=None, help="the final recipe (default: the summary's, else beta6_from_alpha2)")
    args = parser.parse_args(argv)
    scale = args.results.name
    final = args.final or "beta6_from_alpha2"
    summary = read_json(ResultsTree(args.results).report("summary.json")) or {}
    final = summary.get("final_recipe", final)
    try:
        log = args.log or step_times.newest_log(Path.cwd())
    except ConfigError:
        log = None
    try:
        out = write_card(args.results, final, scale, args.start, log)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"results card: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
