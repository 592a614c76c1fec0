"""The report's figures: quality against fine-tuning time and against render time (dissertation figures 57-58) with
the baselines drawn as lines, the published methods on their own axes, and copies of the steps' figures."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from avatarlab.report.published import PUBLISHED_SECONDS, PUBLISHED_TABLE2
from avatarlab.runtime.io import atomic_path


def save_figure(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def first_below(curve: list[dict], metric: str, level: float) -> dict | None:
    """The first point of a quality-vs-time curve whose `metric` is below `level` (e.g. where the avatar's ST-LPIPS
    drops below the nearest training frame's), None if it never does."""
    return next((pt for pt in curve if pt.get(metric) is not None and pt[metric] < level), None)


def quality_figures(avatars: list[dict], final: str, folder: Path) -> list[Path]:
    """Figures 57-58 for this run: test quality against fine-tuning time (a curve per avatar, from the weights kept
    part-way) and against render time per frame, each subject's best trivial baseline drawn as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finals = [a for a in avatars if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a"
              and a["seed"] == 0]
    colours = {s: f"C{i}" for i, s in enumerate(sorted({a["subject"] for a in avatars}))}
    written = []
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.8))
    panels = (("psnr", "test PSNR (dB)", max), ("ssim", "test SSIM", max), ("st_lpips", "test ST-LPIPS (lower is better)",
                                                                             min))
    for a in finals:
        curve = [pt for pt in a["eval"].get("curve", []) if pt.get("seconds") is not None]
        base = a["eval"]["all"]["baselines"]
        colour = colours[a["subject"]]
        for ax, (metric, _, pick) in zip(axes, panels):
            points = [pt for pt in curve if pt.get(metric) is not None]
            if points:
                ax.plot([pt["seconds"] for pt in points], [pt[metric] for pt in points], "o-", ms=3, color=colour,
                        label=f"{a['subject']} (final recipe)")
            scored = [b[metric] for b in base.values() if b.get(metric) is not None]
            if scored:
                ax.axhline(pick(scored), ls="--", lw=1, color=colour, alpha=0.7)
            nearest = (base.get("nearest") or {}).get(metric)
            if metric == "st_lpips" and nearest is not None:  # where the avatar gets sharper than a copied frame
                ax.axhline(nearest, ls=":", lw=1, color=colour, alpha=0.9)
                cross = first_below(points, metric, nearest)
                if cross is not None:
                    ax.annotate(f"below nearest frame at {cross['seconds']:.0f} s", (cross["seconds"], cross[metric]),
                                fontsize=6, color=colour, xytext=(4, -10), textcoords="offset points")
    for ax, (_, label, _) in zip(axes, panels):
        ax.set_xlabel("fine-tuning time on this CPU (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7)
    fig.suptitle("quality vs creation time (dashed: each subject's best trivial baseline on the same frames; dotted: "
                 "its nearest training frame's ST-LPIPS)", fontsize=9)
    fig.tight_layout()
    written.append(save_figure(fig, folder / "time_vs_quality.png"))
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    for a in (a for a in avatars if a["variant"] == "a"):
        m = a["eval"]["all"]["model"]
        ax.scatter(a["eval"]["render_seconds_per_frame"], m["psnr"], s=14, color=colours[a["subject"]],
                   marker="o" if a["recipe"] == "final" else ".", alpha=0.8)
    for subject, colour in colours.items():
        runs = [a for a in avatars if a["subject"] == subject]
        if runs:
            best = max(runs[0]["eval"]["all"]["baselines"].values(), key=lambda b: b["psnr"])["psnr"]
            ax.axhline(best, ls="--", lw=1, color=colour, label=f"{subject}: best baseline")
    ax.set_xlabel("render time per frame, CPU (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title("quality vs render time (o final recipe, . ablation fine-tunes)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    written.append(save_figure(fig, folder / "render_time_vs_quality.png"))
    fig, ax = plt.subplots(figsize=(5, 3.6))  # the published methods on their own axes (other data and hardware)
    for row in PUBLISHED_TABLE2:
        ax.scatter(PUBLISHED_SECONDS[row["method"]], row["psnr"], s=30)
        ax.annotate(row["method"], (PUBLISHED_SECONDS[row["method"]], row["psnr"]), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("creation time on an RTX 4090 (s), published")
    ax.set_ylabel("PSNR (dB), published")
    ax.set_title("dissertation figure 57 (published numbers)", fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return written + [save_figure(fig, folder / "published_time_vs_quality.png")]


def copy_figure(src: Path, dst: Path) -> Path | None:
    if not src.is_file():
        return None
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    return dst


def labelled_grid(rows: list[tuple[str, np.ndarray]], columns: list[str], min_cell: int = 160) -> np.ndarray:
    """A figure of image rows (each (H, W*k, 3) uint8, k cells side by side) with each row's label on the left and
    each column's on top, cells enlarged (nearest neighbour) to at least `min_cell` pixels: what a reader of the
    report can read. -> (H', W', 3) uint8."""
    from PIL import Image, ImageDraw, ImageFont

    h = rows[0][1].shape[0]
    k = len(columns)
    scale = max(1, -(-min_cell // h))
    cell = h * scale
    left, top = 150, 28
    canvas = Image.new("RGB", (left + k * cell, top + len(rows) * cell), "white")
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default(size=15)
    for c, label in enumerate(columns):
        draw.text((left + c * cell + 6, 6), label, fill="black", font=font)
    for r, (label, image) in enumerate(rows):
        big = Image.fromarray(image).resize((image.shape[1] * scale, h * scale), Image.NEAREST)
        canvas.paste(big, (left, top + r * cell))
        draw.multiline_text((6, top + r * cell + cell // 2 - 10), label.replace(": ", ":\n"), fill="black", font=font)
    return np.asarray(canvas)
