"""The report: every table and figure of the reproduction, built only from the metrics files the runs wrote.

Tables (CSV + Markdown) in `<report>/tables/`: preprocessing, pretraining (14 models + renderer experiment),
alpha1 vs alpha2 avatars, beta1-beta6 avatars per subject (figures 39-42 of the dissertation), the interpolation
experiment (figure 54), table 2 with the dissertation's published rows beside ours, and the applications.
Figures in `<report>/figures/`: quality vs creation time and vs per-frame render time (figures 57-58), and the image
grids (test frames, novel views and sweeps, expression transfer). `<report>/README.md` puts them together.
A number missing from a run (LPIPS without the backbone weights, identity without a detected face) is written as
"missing", never filled in.
`python -m avatarlab.evaluate.report report.results_dir=results/tiny`
"""
from __future__ import annotations

import csv
import io
import json
import logging
import shutil
from pathlib import Path

import hydra
from omegaconf import DictConfig

from avatarlab.config import CONF_DIR
from avatarlab.io import atomic_path

log = logging.getLogger(__name__)

MISSING = "missing"
# Table 2 of the dissertation (seed 002, section 4.5): INSTA data, 256x256, creation time on an RTX 4090.
PUBLISHED_TABLE2 = [
    {"method": "NHA", "psnr": 25.1049, "ssim": 0.8080, "lpips": 0.0789, "creation_time": "~8 h"},
    {"method": "IMAvatar", "psnr": 25.8890, "ssim": 0.9123, "lpips": 0.0771, "creation_time": "3-7 days"},
    {"method": "PointAvatar", "psnr": 26.2529, "ssim": 0.8862, "lpips": 0.0631, "creation_time": "~1 h"},
    {"method": "INSTA", "psnr": 25.4665, "ssim": 0.9098, "lpips": 0.1066, "creation_time": "~10 min"},
    {"method": "proposed (dissertation)", "psnr": 26.2867, "ssim": 0.8952, "lpips": 0.0461,
     "creation_time": "~10 min"},
]
PUBLISHED_SECONDS = {"NHA": 8 * 3600, "IMAvatar": 5 * 86400, "PointAvatar": 3600, "INSTA": 600,
                     "proposed (dissertation)": 600}
PUBLISHED_INTERP_GAIN_DB = 0.17  # variant (c) over (b), section 4.3
# Seed 000's table (GRID): latency and lip-landmark error normalised by the outer-eye distance.
PUBLISHED_SPEECH = [
    {"method": "NVIDIA (Karras et al. 2017)", "latency_ms": 260, "lip_error_iod": None},
    {"method": "VisemeNet", "latency_ms": 950, "lip_error_iod": 2.5},
    {"method": "seed 000, with regularisation", "latency_ms": 130, "lip_error_iod": 1.9},
    {"method": "seed 000, without regularisation", "latency_ms": 130, "lip_error_iod": 2.1},
]


def fmt(value, digits: int = 4):
    if value is None:
        return MISSING
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


class Table:
    def __init__(self, name: str, title: str, columns: list[str], note: str = ""):
        self.name, self.title, self.columns, self.note, self.rows = name, title, columns, note, []

    def add(self, **row):
        self.rows.append(row)

    def csv(self) -> str:
        out = io.StringIO()
        writer = csv.DictWriter(out, self.columns, extrasaction="ignore")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({c: "" if row.get(c) is None else row.get(c) for c in self.columns})
        return out.getvalue()

    def markdown(self) -> str:
        lines = [f"### {self.title}", ""]
        if self.note:
            lines += [self.note, ""]
        lines += ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        for row in self.rows:
            lines.append("| " + " | ".join(fmt(row.get(c)) for c in self.columns) + " |")
        if not self.rows:
            lines.append("| " + " | ".join(["(no runs)"] + [""] * (len(self.columns) - 1)) + " |")
        return "\n".join(lines) + "\n"

    def write(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        for suffix, text in ((".csv", self.csv()), (".md", self.markdown())):
            with atomic_path(folder / f"{self.name}{suffix}") as tmp:
                tmp.write_text(text)


def read_json(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def load_avatars(results: Path) -> list[dict]:
    """Every avatar's metrics.json: avatars/<subject>/<init>/metrics.json (variant a) and
    avatars/<subject>/<init>_frames<b|c>/metrics.json (the interpolation variants)."""
    runs = []
    for path in sorted(results.glob("avatars/*/*/metrics.json")):
        run = json.loads(path.read_text())
        run["dir"] = str(path.parent)
        run.setdefault("frames_variant", "a")
        runs.append(run)
    return runs


def avatar_row(run: dict, part: str = "all") -> dict:
    t = run["test"][part]
    return {"subject": run["subject"], "init": run["init"], "variant": run.get("frames_variant", "a"),
            "train_frames": run["train_frames"], "test_frames": t["frames"], "psnr": t["psnr"], "ssim": t["ssim"],
            "lpips": t["lpips"], "identity": t["identity_similarity"], "iterations": run["iterations"],
            "train_seconds": run["train_seconds"], "render_s_per_frame": run["test"]["render_seconds_per_frame"]}


def preprocessing_table(results: Path) -> Table:
    table = Table("preprocessing", "Preprocessing per subject",
                  ["subject", "frames", "landmarks_found", "landmark_nme_vs_truth", "mask_iou", "fit_landmark_px",
                   "fit_shape_mm", "fit_expression_mm", "fit_jaw_deg", "rgbd_accuracy_mm", "rgbd_vertex_mm",
                   "interp_xvfi_psnr", "interp_farneback_psnr", "interp_crossfade_psnr"],
                  "Errors against ground truth exist only for synthetic subjects; RGBD only where depth exists "
                  "(synthetic). RGBD accuracy = sqrt(Loss3), the dissertation reports 0.2 mm on its stereo data.")
    for folder in sorted(p for p in (results / "subjects").glob("*") if (p / "fit_rgb.json").is_file()):
        lm, masks, fit = (read_json(folder / f) or {} for f in ("landmarks.json", "masks.json", "fit_rgb.json"))
        rgbd, interp = read_json(folder / "fit_rgbd.json") or {}, read_json(folder / "interp.json") or {}
        truth = fit.get("truth", {})
        table.add(subject=folder.name, frames=fit.get("frames"), landmarks_found=lm.get("detection_rate"),
                  landmark_nme_vs_truth=lm.get("nme_mean"), mask_iou=masks.get("iou_mean"),
                  fit_landmark_px=fit.get("landmark_error_px"), fit_shape_mm=truth.get("shape_error_mm"),
                  fit_expression_mm=truth.get("expression_error_mm"), fit_jaw_deg=truth.get("jaw_error_deg"),
                  rgbd_accuracy_mm=rgbd.get("accuracy_mm"), rgbd_vertex_mm=rgbd.get("vertex_error_mm"),
                  interp_xvfi_psnr=(interp.get("xvfi") or {}).get("psnr"),
                  interp_farneback_psnr=(interp.get("farneback") or {}).get("psnr"),
                  interp_crossfade_psnr=(interp.get("cross_fade") or {}).get("psnr"))
    return table


def pretraining_tables(results: Path) -> tuple[Table, Table]:
    table = Table("pretraining", "Pretrained head models (held-out head-model renders)",
                  ["model", "strategy", "iterations", "seconds", "samples_per_second", "eval_psnr",
                   "eval_psnr_head", "eval_ssim", "perceptual"],
                  "The dissertation's claim: alpha renders match FLAME renders at PSNR ~30 dB (paper scale).")
    for path in sorted(results.glob("pretrain/*/metrics.json")):
        if path.parent.name.startswith("renderer_"):
            continue
        run = json.loads(path.read_text())
        table.add(model=run.get("name") or run["strategy"], strategy=run["strategy"], iterations=run["iterations"],
                  seconds=run["seconds"], samples_per_second=run.get("samples_per_second"),
                  eval_psnr=run["eval"]["psnr"], eval_psnr_head=run["eval"].get("psnr_head"),
                  eval_ssim=run["eval"]["ssim"], perceptual=run.get("perceptual"))
    renderer = Table("renderer_experiment", "Renderer experiment (proposed vs HeadNeRF-style baseline)",
                     ["renderer", "iterations_to_target", "final_psnr", "eval_psnr", "seconds", "iteration_ratio",
                      "claim_holds"],
                     "Claim (dissertation): the proposed renderer needs fewer than half the iterations (ratio > 2).")
    exp = read_json(results / "report" / "renderer_experiment.json")
    if exp:
        for name in ("proposed", "baseline"):
            renderer.add(renderer=name, iterations_to_target=exp["iterations_to_target"].get(name),
                         final_psnr=exp["final_psnr"].get(name), eval_psnr=exp["eval"][name]["psnr"],
                         seconds=exp["seconds"][name], iteration_ratio=exp["iteration_ratio"],
                         claim_holds=exp["claim_holds"])
    return table, renderer


AVATAR_COLUMNS = ["subject", "init", "variant", "train_frames", "test_frames", "psnr", "ssim", "lpips", "identity",
                  "train_seconds", "render_s_per_frame"]


def alpha_table(avatars: list[dict]) -> Table:
    table = Table("alpha1_vs_alpha2", "Avatars initialised from alpha1 vs alpha2 (all test frames and mouth-open subset)",
                  ["subject", "init", "subset", "test_frames", "psnr", "ssim", "lpips", "identity"],
                  "The mouth-open subset = the test frames with the widest fitted jaw opening (the dissertation: "
                  "30 per subject). alpha2 adds the mouth interior in its last pretraining phase.")
    for run in avatars:
        if run["init"] in ("alpha1", "alpha2") and run["frames_variant"] == "a":
            for part in ("all", "mouth_open"):
                row = avatar_row(run, part)
                table.add(subset=part, **{k: row[k] for k in ("subject", "init", "test_frames", "psnr", "ssim",
                                                              "lpips", "identity")})
    return table


def beta_table(avatars: list[dict]) -> Table:
    table = Table("beta_ablation", "Avatars initialised from beta1-beta6 continued from alpha1 / alpha2 "
                  "(dissertation figures 39-42)", AVATAR_COLUMNS,
                  "beta1: real only; beta2: + z-augmentation; beta3: p=0.25; beta4: p 0.25->0; beta5: beta3 + z-aug; "
                  "beta6: beta4 + z-aug (the final recipe, from alpha2).")
    for run in sorted(avatars, key=lambda r: (r["subject"], r["init"].split("_from_")[-1], r["init"])):
        if "_from_" in run["init"] and run["frames_variant"] == "a":
            table.add(**avatar_row(run))
    return table


def interp_table(avatars: list[dict], results: Path) -> Table:
    table = Table("interpolation", "Interpolation experiment (dissertation figure 54): (a) all frames, (b) every "
                  "second frame dropped, (c) (b) + interpolated frames", AVATAR_COLUMNS + ["gain_c_over_b_db"],
                  f"Published: (c) is {PUBLISHED_INTERP_GAIN_DB} dB PSNR above (b). Variant (c)'s new frames come from "
                  "the XVFI-style network; their parameters are the neighbours' mean (no fit of the new frame).")
    by_subject: dict[str, dict[str, dict]] = {}
    for run in avatars:
        by_subject.setdefault(run["subject"], {})
        name = run["init"]
        if run["frames_variant"] in ("b", "c") or (run["frames_variant"] == "a" and any(
                r["subject"] == run["subject"] and r["init"] == name and r["frames_variant"] in ("b", "c")
                for r in avatars)):
            by_subject[run["subject"]][run["frames_variant"]] = run
    for subject, variants in sorted(by_subject.items()):
        gain = None
        if "b" in variants and "c" in variants:
            gain = variants["c"]["test"]["all"]["psnr"] - variants["b"]["test"]["all"]["psnr"]
        for v in ("a", "b", "c"):
            if v in variants:
                table.add(**avatar_row(variants[v]), gain_c_over_b_db=gain if v == "c" else None)
    return table


def comparison_table(avatars: list[dict], final_recipe: str, scale: str) -> Table:
    table = Table("table2_comparison", "Table 2: published methods (dissertation) beside this run",
                  ["source", "method", "data", "psnr", "ssim", "lpips", "creation_time"],
                  "Rows marked 'published' are copied from the dissertation (INSTA videos, 256x256, RTX 4090); rows "
                  f"marked 'this run' come from this workflow at scale '{scale}' on the data named, on CPU. They are "
                  "not the same data or budget and are shown side by side only as labelled.")
    for row in PUBLISHED_TABLE2:
        table.add(source="published", data="INSTA, 256x256", **row)
    for run in avatars:
        if run["init"] == final_recipe and run["frames_variant"] == "a":
            t = run["test"]["all"]
            table.add(source="this run", method=f"avatarlab ({final_recipe})",
                      data=f"{run['subject']}, {scale}", psnr=t["psnr"], ssim=t["ssim"], lpips=t["lpips"],
                      creation_time=f"{run['train_seconds']:.0f} s fine-tuning (CPU)")
    return table


def applications_table(results: Path) -> Table:
    table = Table("applications", "Applications: telepresence payload and expression transfer",
                  ["subject", "values_per_frame", "params_float16_bytes", "params_float32_bytes", "jpeg_bytes",
                   "jpeg_over_float16", "float16_render_psnr_db", "receiver_render_s_per_frame",
                   "transfer_frames", "transfer_render_s_per_frame"])
    for path in sorted(results.glob("apps/*/telepresence.json")):
        tel = json.loads(path.read_text())
        transfer = next((json.loads(p.read_text()) for p in sorted(path.parent.glob("reenact_*.json"))), {})
        jpeg_key = next(iter(tel["jpeg_bytes_per_frame"]))
        table.add(subject=path.parent.name, values_per_frame=tel["values_per_frame"],
                  params_float16_bytes=tel["bytes_per_frame"]["params_float16"],
                  params_float32_bytes=tel["bytes_per_frame"]["params_float32"],
                  jpeg_bytes=f"{tel['jpeg_bytes_per_frame'][jpeg_key]:.0f} ({jpeg_key})",
                  jpeg_over_float16=tel["jpeg_over_float16_ratio"], float16_render_psnr_db=tel["float16_render_psnr_db"],
                  receiver_render_s_per_frame=tel["receiver_render_seconds_per_frame"],
                  transfer_frames=transfer.get("frames"), transfer_render_s_per_frame=transfer.get(
                      "render_seconds_per_frame"))
    return table


def speech_table(results: Path, scale: str) -> Table:
    table = Table("speech", "Speech-driven animation (seed 000's table; seed 001's window model)",
                  ["source", "method", "data", "latency_ms", "lip_error_iod", "compute_ms_per_step",
                   "real_time_factor", "train_seconds"],
                  "lip_error_iod: mean lip-landmark error / outer-eye distance, in percent (the published values "
                  "are read as percent too). Published rows: GRID (34 speakers, 24/6/4 split). 'this run' rows: the "
                  f"synthetic espeak-ng corpus at scale '{scale}', test speakers unseen in training; the window model "
                  "(seed 001) is given the true phoneme labels, the others only audio.")
    for row in PUBLISHED_SPEECH:
        table.add(source="published", data="GRID", **row)
    names = {"lstm_reg": "seed 000, with regularisation", "lstm_noreg": "seed 000, without regularisation",
             "window": "seed 001 sliding window (phonemes in)"}
    for key, label in names.items():
        run = read_json(results / "speech" / key / "metrics.json")
        if run:
            t = run["test"]
            table.add(source="this run", method=label, data=f"synthetic corpus, {scale}", latency_ms=t["latency_ms"],
                      lip_error_iod=t["lip_error_percent"], compute_ms_per_step=t.get("compute_ms_per_step"),
                      real_time_factor=t.get("real_time_factor"), train_seconds=run["train_seconds"])
    window = read_json(results / "speech" / "window" / "metrics.json")
    if window and window["test"].get("retargeted_lip_error_percent") is not None:
        table.add(source="this run", method="  seed 001 retargeted to the head model's rig (+-3 sigma poses), "
                  "motion only (identity offset removed)", data=f"synthetic corpus, {scale}",
                  lip_error_iod=window["test"]["retargeted_lip_error_percent"])
    grid = read_json(results / "speech" / "grid_eval.json")
    if grid:
        table.add(source="this run", method="seed 000 with regularisation, trained on the synthetic corpus",
                  data=f"{len(grid['clips'])} real GRID clips", latency_ms=None,
                  lip_error_iod=grid["lip_error_percent"])
        table.add(source="this run", method="  same, each clip's identity offset removed",
                  data=f"{len(grid['clips'])} real GRID clips", lip_error_iod=grid["lip_error_identity_normalised_percent"])
        table.add(source="this run", method="  a still mouth at each clip's mean shape (baseline)",
                  data=f"{len(grid['clips'])} real GRID clips", lip_error_iod=grid["static_mouth_baseline_percent"])
    return table


def quality_figures(avatars: list[dict], final_recipe: str, folder: Path) -> list[Path]:
    """Figures 57-58: avatar quality vs creation (training) time and vs per-frame render time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    runs = [r for r in avatars if r["frames_variant"] == "a"]
    for name, key, xlabel in (("time_vs_quality", "train_seconds", "fine-tuning time on this CPU (s)"),
                              ("render_time_vs_quality", "render_s_per_frame", "render time per frame, CPU (s)")):
        metrics = [("psnr", "PSNR (dB)"), ("ssim", "SSIM")]
        if any(r["test"]["all"]["lpips"] is not None for r in runs):
            metrics.append(("lpips", "LPIPS"))
        fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6))
        for ax, (metric, label) in zip(axes, metrics):
            for subject in sorted({r["subject"] for r in runs}):
                pts = [avatar_row(r) for r in runs if r["subject"] == subject and r["test"]["all"][metric] is not None]
                ax.scatter([p[key] for p in pts], [p[metric] for p in pts], s=18, label=subject, alpha=0.8)
                for p in pts:
                    if p["init"] == final_recipe:
                        ax.annotate("final", (p[key], p[metric]), fontsize=7)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.suptitle("avatars of this run (one point per pretrained initialisation)", fontsize=9)
        fig.tight_layout()
        path = folder / f"{name}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
        written.append(path)
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
    path = folder / "published_time_vs_quality.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return written + [path]


def copy_figure(src: Path, dst: Path) -> Path | None:
    if not src.is_file():
        return None
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    return dst


def build(results: Path, out: Path, final_recipe: str, scale: str) -> dict:
    tables_dir, figures_dir = out / "tables", out / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    avatars = load_avatars(results)
    pre, renderer = pretraining_tables(results)
    tables = [preprocessing_table(results), pre, renderer, alpha_table(avatars), beta_table(avatars),
              interp_table(avatars, results), comparison_table(avatars, final_recipe, scale),
              applications_table(results), speech_table(results, scale)]
    for table in tables:
        table.write(tables_dir)
    figures = quality_figures(avatars, final_recipe, figures_dir) if avatars else []
    for run in avatars:
        if run["init"] == final_recipe and run["frames_variant"] == "a":
            figures.append(copy_figure(Path(run["dir"]) / "test_frames.png",
                                       figures_dir / f"test_frames_{run['subject']}.png"))
    for path in sorted(results.glob("apps/*/*.png")):
        figures.append(copy_figure(path, figures_dir / f"{path.parent.name}_{path.name}"))
    for path in sorted(results.glob("speech/speak_*.png")):
        figures.append(copy_figure(path, figures_dir / path.name))
    figures += [copy_figure(results / "headmodel" / "render_grid.png", figures_dir / "head_model_sweeps.png"),
                copy_figure(results / "report" / "renderer_experiment.png", figures_dir / "renderer_experiment.png")]
    figures = [f for f in figures if f is not None]
    lines = [f"# avatarlab report - scale `{scale}`", "",
             "Every number below was read from a metrics file a workflow step wrote (see `results/` and the MLflow "
             "store); 'missing' means the run could not measure it (e.g. LPIPS without the VGG backbone weights).",
             ""]
    lines += [t.markdown() for t in tables]
    lines += ["## Figures", ""] + [f"![{f.stem}](figures/{f.name})" for f in figures]
    with atomic_path(out / "README.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    summary = {"avatars": len(avatars), "tables": [t.name for t in tables], "figures": [f.name for f in figures],
               "rows": {t.name: len(t.rows) for t in tables}}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return summary


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    rep = cfg.report
    summary = build(Path(rep.results_dir), Path(rep.out_dir), str(rep.final_recipe), cfg.scale.name)
    log.info("report: %d avatars, tables %s, %d figures -> %s", summary["avatars"], summary["rows"],
             len(summary["figures"]), rep.out_dir)


if __name__ == "__main__":
    main()
