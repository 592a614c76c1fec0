"""A sweep's table and figure: one row per setting (the point without its seed) with the metric's mean and 95 % CI
over seeds, the gain over the best trivial baseline, and whether the setting differs from the best one beyond the
seed-to-seed noise; a figure of the metric against each swept value.

`python -m avatarlab.report.sweep_report --sweep conf/sweep/finetune_lr.yaml --dir results/tiny/sweeps/finetune_lr`
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from avatarlab.metrics.scoring import LOWER_IS_BETTER
from avatarlab.metrics.seeds import mean_ci, pooled_sd, single_run_threshold
from avatarlab.report.figures import save_figure
from avatarlab.report.table import MAX_SHOWN, Table
from avatarlab.runtime.io import atomic_path
from avatarlab.workflow.sweeps import CHOOSE_ON, SEED_KEY, Sweep, load_sweep

log = logging.getLogger(__name__)


def point_scores(sweep: Sweep, report: dict) -> tuple[float, float, str, float, dict]:
    """(metric, gain over the best baseline, best baseline's name, its value, the `also` metrics) of one point's
    eval.json; an `also` metric the evaluation did not measure is None."""
    part = report["all"] if sweep.step == "finetune" else report
    gain_key = sweep.metric if sweep.metric in part["gain"] else next(iter(part["gain"]))
    g = part["gain"][gain_key]
    also = {name: part["model"].get(name) for name in sweep.also}
    return part["model"][sweep.metric], g["gain"], g["best_baseline"], g["baseline"], also


def also_columns(sweep: Sweep, runs: list) -> dict:
    """Each `also` metric of one setting: mean and 95 % CI over the seeds that measured it ("missing" if none)."""
    out = {}
    for name in sweep.also:
        mean, ci, _ = mean_ci(s[5][name] for s in runs)
        out.update({name: "missing" if mean is None else mean, f"{name}_ci95": ci})
    return out


def validation_scores(folder: Path) -> dict[str, float | None]:
    """The validation scores (CHOOSE_ON: psnr, st_lpips) of the avatar a fine-tuning point chose (its train.json, read
    once); None without a validation split or where a score was not recorded."""
    path = folder / "train.json"
    report = json.loads(path.read_text()) if path.is_file() else {}
    chosen = [s for s in report.get("validation_scores") or [] if s.get("step") == report.get("chosen_step")]
    return {on: report[f"validation_{on}"] if report.get(f"validation_{on}") is not None
            else (chosen[0].get(on) if chosen else None) for on in CHOOSE_ON}


def mark_chosen(rows: list[dict], on: str = "psnr") -> str:
    """Marks the setting with the best mean validation score `chosen` (`on`: the highest PSNR or the lowest
    ST-LPIPS; the choice, the test columns only score it); without validation scores for every setting nothing is
    chosen. -> the note's sentence about it."""
    key = f"validation_{on}"
    for r in rows:
        r["chosen"] = ""
    if not rows or any(r[key] is None for r in rows):
        return ("No validation split (finetune.validation_frames / validation_clips = 0) or no validation "
                f"{on} recorded: this sweep chooses nothing; its best-on-test row is a score, not a choice.")
    pick = (min if on in LOWER_IS_BETTER else max)(rows, key=lambda r: r[key])
    pick["chosen"] = "chosen"
    label = {"psnr": "PSNR", "st_lpips": "ST-LPIPS"}[on]
    return (f"chosen: the setting with the best mean validation {label} (frames held out before the test frames, "
            "train.json); the test columns only score it.")


def summarise(sweep: Sweep, folder: Path) -> tuple[Table, list[dict]]:
    by_setting: dict[tuple, list] = {}
    for point in sweep.points:
        report = json.loads((folder / point.name / "eval.json").read_text())
        by_setting.setdefault(point.setting, []).append((point, *point_scores(sweep, report),
                                                         validation_scores(folder / point.name)))
    swept = [k for k in sweep.keys if k != SEED_KEY]
    sd, dof = pooled_sd([[s[1] for s in runs] for runs in by_setting.values()])
    rows = []
    for setting, runs in by_setting.items():
        mean, ci, n = mean_ci(s[1] for s in runs)
        gain, gain_ci, _ = mean_ci(s[2] for s in runs)
        rows.append({**{k: v for k, v in setting}, "seeds": n, sweep.metric: mean, f"{sweep.metric}_ci95": ci,
                     "gain": gain, "gain_ci95": gain_ci, "best_baseline": runs[0][3], "baseline": runs[0][4],
                     **also_columns(sweep, runs), "values": [s[1] for s in runs],
                     **{f"validation_{on}": None if any(s[6][on] is None for s in runs)
                        else mean_ci(s[6][on] for s in runs)[0] for on in CHOOSE_ON}})
    choice = mark_chosen(rows, sweep.choose_on)
    lower = sweep.metric in LOWER_IS_BETTER
    best = (min if lower else max)(rows, key=lambda r: r[sweep.metric])
    threshold = single_run_threshold(sd)
    for r in rows:  # how much worse than the best setting, in the metric's own direction
        r["worse_than_best"] = (r[sweep.metric] - best[sweep.metric]) if lower else (best[sweep.metric] - r[sweep.metric])
        if sd is None:
            r["differs_from_best"] = None
        else:  # two means of n and m seeds: the noise of their difference is sd * sqrt(1/n + 1/m)
            limit = 1.96 * sd * ((1 / r["seeds"] + 1 / best["seeds"]) ** 0.5)
            r["differs_from_best"] = ("best" if r is best else
                                      "yes" if r["worse_than_best"] > limit else "no (within noise)")
    columns = swept + ["seeds", "validation_psnr", "validation_st_lpips", "chosen", sweep.metric,
                       f"{sweep.metric}_ci95", "gain", "gain_ci95", "best_baseline", "baseline", "worse_than_best",
                       "differs_from_best"]
    columns += [c for name in sweep.also for c in (name, f"{name}_ci95")]
    note = (f"{sweep.description or sweep.name}. {len(sweep.points)} points ({sweep.step}); metric: test "
            f"{sweep.metric} ({'lower' if lower else 'higher'} is better), mean over seeds with its 95 % CI (Student's "
            "t); gain over the best trivial baseline on "
            f"the same frames. differs_from_best: whether the gap to the best setting exceeds 1.96 x the "
            f"seed-to-seed SD of a difference of means" + (f" (pooled SD {sd:.3f}, {dof} degrees of freedom)."
                                                           if sd is not None else " (one seed per setting: no verdict)."))
    if threshold is not None:
        note += f" Two single runs differ beyond noise above {threshold:.2f}."
    note += " " + choice
    if sweep.also:
        note += f" Beside it, each setting's mean and 95 % CI over seeds of: {', '.join(sweep.also)}."
    shown = swept + ["seeds", f"validation_{sweep.choose_on}", "chosen", sweep.metric, "gain", "differs_from_best"]
    table = Table(f"sweep_{sweep.name}", f"Sweep {sweep.name}", columns, note,
                  shown=shown + list(sweep.also)[:max(0, MAX_SHOWN - len(shown))])
    for r in sorted(rows, key=lambda r: tuple(str(r[k]) for k in swept)):
        table.add(**{k: (str(v) if isinstance(v, (list, tuple)) else v) for k, v in r.items()})
    return table, rows


def baseline_line(ax, value: float, name: str, points: list[float]) -> None:
    """The best baseline as a dashed line where it lies near the points; far from them (a baseline 10 dB away would
    flatten 0.1 dB differences) the axis keeps to the points and an arrow at its edge gives the baseline's value."""
    low, high = min(points), max(points)
    span = max(high - low, 1e-6)
    label = f"best baseline ({name}): {value:.2f}"
    if low - 2 * span <= value <= high + 2 * span:
        ax.axhline(value, ls="--", lw=1, color="C3", label=label)
        return
    ax.set_ylim(low - 0.3 * span, high + 0.3 * span)
    above = value > high
    ax.annotate(f"{label} {'above' if above else 'below'}", xy=(0.5, 0.98 if above else 0.02),
                xycoords="axes fraction", ha="center", va="top" if above else "bottom", fontsize=7, color="C3",
                arrowprops=None)
    ax.plot([], [], ls="--", color="C3", label=label)


def figure(sweep: Sweep, rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    swept = [k for k in sweep.keys if k != SEED_KEY] or ["point"]
    fig, axes = plt.subplots(1, len(swept), figsize=(4.2 * len(swept), 3.4), squeeze=False)
    for ax, key in zip(axes[0], swept):
        groups: dict = {}
        for r in rows:
            groups.setdefault(str(r.get(key)), []).extend(r["values"])
        labels = list(groups)
        stats = [mean_ci(groups[k]) for k in labels]
        x = range(len(labels))
        ax.errorbar(list(x), [s[0] for s in stats], yerr=[s[1] or 0.0 for s in stats], fmt="o-", capsize=4)
        for i, k in enumerate(labels):
            ax.scatter([i] * len(groups[k]), groups[k], s=8, color="grey", alpha=0.6)
        baseline_line(ax, rows[0]["baseline"], rows[0]["best_baseline"], [v for k in labels for v in groups[k]])
        ax.set_xticks(list(x), labels, fontsize=8)
        ax.set_xlabel(key)
        ax.set_ylabel(f"test {sweep.metric}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"sweep {sweep.name}: mean over seeds, 95 % CI; grey: single runs", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sweep", type=Path, required=True, help="conf/sweep/<name>.yaml")
    parser.add_argument("--dir", type=Path, required=True, help="results/<scale>/sweeps/<name>")
    parser.add_argument("--seeds", type=int, default=None,
                        help="seeds 0..n-1 instead of the file's seed axis (workflow config sweep_seeds)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sweep = load_sweep(args.sweep, args.seeds)
    table, rows = summarise(sweep, args.dir)
    for suffix, text in ((".md", table.markdown()), (".csv", table.csv())):
        with atomic_path(args.dir / f"table{suffix}") as tmp:
            tmp.write_text(text)
    figure(sweep, rows, args.dir / "figure.png")
    log.info("sweep %s: %d settings -> %s", sweep.name, len(rows), args.dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
