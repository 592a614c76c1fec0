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
`python -m avatarlab.evaluate.report report.results_dir=results/tiny`
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from avatarlab.entry import entry_point
from avatarlab.evaluate.claims import PUBLISHED_INTERP_GAIN_DB, claims_table
from avatarlab.evaluate.runs import load_avatars, load_runs, seed_noise, seeded_runs
from avatarlab.evaluate.table import MISSING, Table, fmt, read_json  # noqa: F401 (MISSING, fmt: the report's API)
from avatarlab.io import atomic_path
from avatarlab.seed_stats import gain_verdict, mean_ci, paired_difference, signed_range, single_run_threshold

log = logging.getLogger(__name__)
READS = ('report',)  # the config sections this step reads (avatarlab/entry.py)

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
# Seed 000's table (GRID): latency and lip-landmark error normalised by the outer-eye distance.
PUBLISHED_SPEECH = [
    {"method": "NVIDIA (Karras et al. 2017)", "latency_ms": 260, "lip_error_iod": None},
    {"method": "VisemeNet", "latency_ms": 950, "lip_error_iod": 2.5},
    {"method": "seed 000, with regularisation", "latency_ms": 130, "lip_error_iod": 1.9},
    {"method": "seed 000, without regularisation", "latency_ms": 130, "lip_error_iod": 2.1},
]


#: where this platform uses something other than the dissertation (seed 002) or the speech papers, and why
SUBSTITUTIONS = [
    ("head model", "FLAME 2020", "a procedural FLAME-structured head (same joints, blend shapes, 68-point "
     "embedding, PCA albedo, SH lighting)", "FLAME's licence; the real model is used when given by path"),
    ("real image set", "FFHQ (70 000 photographs)", "procedurally varied portraits of the head model (hair caps, "
     "backgrounds, lighting, noise), preprocessed and fitted like photographs", "licence, no downloads; real photos "
     "by path"),
    ("avatar videos", "INSTA's videos", "two synthetic subject videos with ground truth, and the obama clips where "
     "present", "licence, no downloads"),
    ("landmarks", "FAN", "dlib's 68-point detector (face_recognition_models)", "no downloaded weights"),
    ("head masks", "BiSeNet face parsing", "GrabCut seeded from the landmarks, smoothed over time",
     "no downloaded weights"),
    ("perceptual loss", "VGG16 (ImageNet)", "fixed random-conv features unless VGG16 weights are given",
     "ImageNet weights are a licensed optional input"),
    ("LPIPS", "LPIPS-VGG", "LPIPS-VGG only with its backbone given (else 'missing'); ST-LPIPS (AlexNet, weights in "
     "its wheel) reported under its own name", "never a substitute under LPIPS's name"),
    ("frame interpolation", "XVFI trained on X4K1000FPS, its flows learnt from zero", "an XVFI-style multi-scale "
     "flow network trained once on every subject's video (held-out frames excluded) and the synthetic motion "
     "videos of interp_motion_videos, that refines OpenCV's Farneback "
     "flows (interp.flow_init=farneback; zero: XVFI's way)", "no downloaded weights or data; flows learnt from zero "
     "stay a cross-fade within a CPU budget"),
    ("RGBD captures", "ZED2 depth", "the synthetic subjects' rendered depth with Gaussian noise",
     "no depth camera here"),
    ("RGB fit", "free intrinsics", "a fixed principal point (image centre); the root rotation folded into the camera; "
     "the jaw's opening angle kept in fit_rgb.jaw_limits_deg ([-6, 40] degrees)", "stability on short clips; "
     "pretraining uses neck/jaw/eyes, the camera carries the root; a fit once turned the jaw 48 degrees the closed way"),
    ("RGBD fit", "blocks 1-3 as written", "fixed (known) intrinsics and a small L2 prior on shape/expression",
     "a depth camera's intrinsics are known; the prior keeps noisy frames plausible"),
    ("CNeRF rays", "a fixed [near, far]", "each ray sampled inside the head's bounding sphere in camera space; a learned "
     "background feature composited by 1 - opacity", "fitted heads lie at other distances than a fixed interval"),
    ("sizes (tiny)", "8x384 MLP, 64 samples, 32->256 px, batch 64, 310 000 + 2 500 iterations, 1000 fine-tuning "
     "iterations, 4 of 8 layers frozen, neck range [80, 60, 80] deg", "4x96 MLP, 16 samples, 16->128 px, batch 4, "
     "5 000 + 400 iterations, 600 fine-tuning iterations (the final recipe 1 200), 2 of 4 layers frozen (the final "
     "recipe 1), neck range [30, 40, 20] deg",
     "two CPU cores and two hours; `scale=paper` restores the dissertation's sizes"),
    ("speech corpus", "recorded GRID speakers", "GRID-grammar sentences spoken by seven espeak-ng and three Festival "
     "voices, augmented (channel, reverberation, noise, gain); real GRID and Obama clips as a test set and, the scored "
     "clip or speaker left out, for fine-tuning; no MBROLA voices", "no downloads; GRID audio is not redistributable "
     "here; Debian has no MBROLA voices"),
    ("speech targets and metric", "each speaker's landmarks; lip error on them", "seed 000 learns each speaker's "
     "motion placed on Pr(B0) (the utterance's mean shape removed); the lip error is reported raw and on the motion, "
     "beside a still mouth and a phoneme lookup", "its landmarks are Pr(B0) plus viseme offsets and cannot carry a "
     "speaker's face; a raw error would mostly measure the face"),
    ("256² / 512² models", "the chosen recipe trained at 256² and 512² (300 000 iterations each)", "the final "
     "recipe's model continued from the previous resolution with its own strategy (β6)", "the dissertation names "
     "the resolutions and the iterations, not how each one starts"),
    ("avatar weights (tiny, smoke)", "the last iterate of fine-tuning", "the final recipe's avatar is an "
     "exponential moving average of its weights (scale.finetune_final_ema_decay = 0.99; paper scale: the last "
     "iterate)", "at 1 200 iterations the last iterate overfits the training frames; the average scored higher on "
     "both synthetic subjects in every seed (sweeps finetune_ema, finetune_ema_talk)"),
    ("avatar test split", "INSTA protocol (last 350 frames)", "for multi-clip real subjects the last clip is held out",
     "an avatar must render a recording it never saw"),
]


def substitutions_table() -> "Table":
    table = Table("substitutions", "Substitutions: where this platform differs from the dissertation, and why",
                  ["what", "dissertation", "here", "why"])
    for what, theirs, ours, why in SUBSTITUTIONS:
        table.add(what=what, dissertation=theirs, here=ours, why=why)
    return table


SEEDED = ("psnr", "gain", "ssim", "st_lpips")


def seeded_row(runs: list[dict], part: str = "all") -> dict:
    """One table row for the seeds of an avatar: the mean of each number over seeds, `seeds`, and the 95 % CI
    half-width of PSNR, gain, SSIM and ST-LPIPS (None with one seed)."""
    rows = [avatar_row(a, part) for a in runs]
    row = dict(rows[0])
    for key, value in rows[0].items():
        if isinstance(value, int) and not isinstance(value, bool) and all(r.get(key) == value for r in rows):
            continue  # a count the seeds share (test frames) stays a count
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            row[key] = mean_ci(r.get(key) for r in rows)[0]
    for key in SEEDED:
        row[key], row[f"{key}_ci95"], _ = mean_ci(r.get(key) for r in rows)
    row["seeds"] = len(rows)
    return row


def gain_columns(part: dict, metric: str) -> dict:
    """best baseline's name and value, and the model's gain over it, for one metric of one evaluated part."""
    g = part["gain"].get(metric)
    if g is None:
        return {"best_baseline": None, "baseline": None, "gain": None}
    return {"best_baseline": g["best_baseline"], "baseline": g["baseline"], "gain": g["gain"]}


def not_beating(table: Table, label_keys: tuple[str, ...], gain_key: str = "gain") -> str:
    """A sentence naming the rows whose gain over their best baseline is not positive."""
    rows = [r for r in table.rows if r.get(gain_key) is not None]
    losers = [" / ".join(str(r.get(k)) for k in label_keys) for r in rows if r[gain_key] <= 0]
    if not rows:
        return "No row has a baseline comparison."
    if not losers:
        return f"Every row ({len(rows)}) beats its best trivial baseline."
    return (f"{len(losers)} of {len(rows)} rows do NOT beat their best trivial baseline: {', '.join(losers)}. "
            "Their numbers say nothing about the method.")


def preprocessing_table(results: Path) -> Table:
    table = Table("preprocessing", "Preprocessing per subject",
                  ["subject", "frames", "landmarks_found", "landmark_nme_vs_truth", "mask_iou", "fit_landmark_px",
                   "fit_shape_mm", "fit_expression_mm", "fit_jaw_deg", "rgbd_accuracy_mm", "rgbd_vertex_mm",
                   "interp_xvfi_psnr", "interp_farneback_psnr", "interp_crossfade_psnr", "interp_xvfi_st_lpips",
                   "interp_farneback_st_lpips", "interp_crossfade_st_lpips", "interp_gain_vs_farneback_db",
                   "interp_gain_vs_farneback_ci95", "interp_gain_vs_crossfade_db", "interp_gain_vs_crossfade_ci95",
                   "interp_frames_won_vs_crossfade", "interp_still_flow_px"],
                  "Errors against ground truth exist only for synthetic subjects; RGBD only where depth exists "
                  "(synthetic). RGBD accuracy = sqrt(Loss3), the dissertation reports 0.2 mm on its stereo data. "
                  "The interpolation columns put the XVFI-style network beside its two baselines (Farneback flow, "
                  "cross-fade) on the same held-out frames (only those between two frames of one clip); the gains "
                  "are its mean per-frame PSNR gain over each baseline with the 95 % CI over frames: a gain is one "
                  "only when it exceeds its CI. interp_still_flow_px: flows shorter than it were not warped, the "
                  "length chosen for the subject on its own kept frames.")
    for folder in sorted(p for p in (results / "subjects").glob("*") if (p / "fit_rgb.json").is_file()):
        lm, masks, fit = (read_json(folder / f) or {} for f in ("landmarks.json", "masks.json", "fit_rgb.json"))
        rgbd, interp = read_json(folder / "fit_rgbd.json") or {}, read_json(folder / "interp.json") or {}
        truth = fit.get("truth", {})
        table.add(subject=folder.name, frames=fit.get("frames"), landmarks_found=lm.get("detection_rate"),
                  landmark_nme_vs_truth=lm.get("nme_mean"), mask_iou=masks.get("iou_mean"),
                  fit_landmark_px=fit.get("landmark_error_px"), fit_shape_mm=truth.get("shape_error_mm"),
                  fit_expression_mm=truth.get("expression_error_mm"), fit_jaw_deg=truth.get("jaw_error_deg"),
                  rgbd_accuracy_mm=rgbd.get("accuracy_mm"), rgbd_vertex_mm=rgbd.get("vertex_error_mm"),
                  **{f"interp_{name}_{metric}": (interp.get(key) or {}).get(metric) for metric in ("psnr", "st_lpips")
                     for name, key in (("xvfi", "xvfi"), ("farneback", "farneback"), ("crossfade", "cross_fade"))},
                  **_interp_gains(interp))
    return table


def _interp_gains(interp: dict) -> dict:
    """The preprocessing table's paired columns and the still-flow length from an interp.json (missing for one
    written before them)."""
    paired = interp.get("paired_psnr_gain") or {}
    flow, fade = paired.get("farneback") or {}, paired.get("cross_fade") or {}
    return {"interp_gain_vs_farneback_db": flow.get("mean_db"), "interp_gain_vs_farneback_ci95": flow.get("ci95_db"),
            "interp_gain_vs_crossfade_db": fade.get("mean_db"), "interp_gain_vs_crossfade_ci95": fade.get("ci95_db"),
            "interp_frames_won_vs_crossfade": (f"{fade['wins']}/{fade['frames']}" if fade else None),
            "interp_still_flow_px": interp.get("still_flow_px")}


PRETRAIN_COLUMNS = ["model", "iterations", "seconds", "samples_per_second", "psnr_head", "mean_colour_psnr_head",
                    "nearest_psnr_head", "gain", "psnr", "ssim", "st_lpips", "best_baseline_st_lpips", "lpips"]


def pretraining_table(results: Path) -> Table:
    table = Table("pretraining", "Pretrained head models on held-out head-model renders, beside trivial baselines",
                  PRETRAIN_COLUMNS,
                  "psnr_head: PSNR over the head region (true mask) - the background is grey in every image and "
                  "would flatter a full-image PSNR; gain = psnr_head minus the best baseline's (mean colour inside "
                  "the mask; the training sample nearest in shape, expression, neck, jaw and camera). The "
                  "dissertation's claim: alpha renders match FLAME renders at PSNR ~30 dB (paper scale).")
    for run in load_runs(results, "pretrain/*"):
        if run["name"].startswith("renderer_"):
            continue
        ev, tr = run["eval"], run["train"]
        table.add(model=run["name"], iterations=tr["iterations"], seconds=tr["seconds"],
                  samples_per_second=tr.get("samples_per_second"), psnr_head=ev["model"]["psnr_head"],
                  mean_colour_psnr_head=ev["baselines"]["mean_colour"]["psnr_head"],
                  nearest_psnr_head=ev["baselines"]["nearest"]["psnr_head"], gain=ev["gain"]["psnr_head"]["gain"],
                  psnr=ev["model"]["psnr"], ssim=ev["model"]["ssim"], st_lpips=ev["model"].get("st_lpips"),
                  best_baseline_st_lpips=gain_columns(ev, "st_lpips")["baseline"],
                  lpips=ev["model"].get("lpips"))
    table.note += " " + not_beating(table, ("model",))
    return table


def controls_table(results: Path) -> Table:
    table = Table("controls", "Pretrained models on held-out frames with one control swept (dissertation figures 27, "
                  "29-32)", ["figure", "control", "model", "frames", "psnr_head", "mean_colour_psnr_head",
                             "unswept_psnr_head", "gain", "st_lpips", "best_baseline_st_lpips",
                             "response_correlation"],
                  "Held-out frames: the middle fitted frame of each video subject (never in pretraining), rendered "
                  "by the model and by the head model (with the mouth interior for alpha2 and its continuations) at "
                  "each value of the control. psnr_head: the model against the head model's renders; baselines: "
                  "the frame's mean colour inside each mask, and the render of the frame's own parameters as if "
                  "the control did nothing (unswept). response_correlation: correlation of the model's change "
                  "along the sweep with the head model's (0: ignores the control). One run per model.")
    for path in sorted(results.glob("pretrain/controls/*.json")):
        report = read_json(path)
        for name, r in report["models"].items():
            table.add(figure=path.stem, control=report["control"], model=name, frames=len(report["frames"]),
                      psnr_head=r["model"]["psnr_head"],
                      mean_colour_psnr_head=r["baselines"]["mean_colour"]["psnr_head"],
                      unswept_psnr_head=(r["baselines"].get("unswept") or {}).get("psnr_head"),
                      gain=r["gain"]["psnr_head"]["gain"], st_lpips=r["model"].get("st_lpips"),
                      best_baseline_st_lpips=gain_columns(r, "st_lpips")["baseline"],
                      response_correlation=r["response_correlation"])
    table.note += " " + not_beating(table, ("figure", "model"))
    return table


def renderer_table(results: Path) -> Table:
    table = Table("renderer_experiment", "Renderer experiment (proposed vs HeadNeRF's block)",
                  ["renderer", "iterations_to_target", "target_psnr", "final_train_psnr", "eval_psnr_head",
                   "eval_best_baseline_psnr_head", "eval_gain", "eval_st_lpips", "eval_best_baseline_st_lpips",
                   "seconds", "iteration_ratio", "claim_holds"],
                  "Claim (dissertation): the proposed renderer needs fewer than half the iterations (ratio > 2) to "
                  "reach the PSNR the baseline renderer ends with.")
    exp = read_json(results / "report" / "renderer_experiment.json")
    if exp:
        for name in ("proposed", "baseline"):
            ev = exp["eval"][name]
            table.add(renderer=name, iterations_to_target=exp["iterations_to_target"].get(name),
                      target_psnr=exp["target_psnr"], final_train_psnr=exp["final_psnr"].get(name),
                      eval_psnr_head=ev["model"]["psnr_head"],
                      eval_best_baseline_psnr_head=ev["gain"]["psnr_head"]["baseline"],
                      eval_gain=ev["gain"]["psnr_head"]["gain"], eval_st_lpips=ev["model"].get("st_lpips"),
                      eval_best_baseline_st_lpips=gain_columns(ev, "st_lpips")["baseline"],
                      seconds=exp["seconds"][name],
                      iteration_ratio=exp["iteration_ratio"], claim_holds=exp["claim_holds"])
        learned = exp.get("renderers_beat_baselines")
        table.note += (f" The target ({exp['target_psnr']:.2f} dB) and iterations_to_target are read on training "
                       "batches; whether each renderer learned anything is judged on held-out frames, where the model "
                       "and its trivial predictors score the same frames (eval_gain): "
                       + ("both beat them." if learned else "NOT both beat them, so the claim cannot be judged "
                          "at this budget." if learned is False else "not recorded."))
        table.note += " " + not_beating(table, ("renderer",), "eval_gain")
    return table


AVATAR_COLUMNS = ["subject", "recipe", "init", "variant", "subset", "test_frames", "psnr", "best_baseline",
                  "baseline_psnr", "gain", "colour_matched_gain", "ssim", "st_lpips", "lpips", "face_detection_rate",
                  "landmark_nme", "identity_similarity", "train_seconds"]


SEEDED_COLUMNS = ["seeds", "psnr_ci95", "gain_ci95", "ssim_ci95", "st_lpips_ci95"]


def avatar_row(avatar: dict, part: str = "all") -> dict:
    ev = avatar["eval"]
    scores = ev[part]
    m = scores["model"]
    g = gain_columns(scores, "psnr")
    return {"subject": avatar["subject"], "recipe": avatar["recipe"], "init": avatar["init"],
            "variant": avatar["variant"], "subset": part, "test_frames": scores["frames"], "psnr": m["psnr"],
            "best_baseline": g["best_baseline"], "baseline_psnr": g["baseline"], "gain": g["gain"],
            "colour_matched_gain": gain_columns(scores, "psnr_head_colour")["gain"], "ssim": m["ssim"],
            "st_lpips": m.get("st_lpips"), "lpips": m.get("lpips"),
            "face_detection_rate": m.get("face_detection_rate"), "landmark_nme": m.get("landmark_nme"),
            "identity_similarity": m.get("identity_similarity"), "train_seconds": avatar["train"]["train_seconds"]}


def final_avatar_table(avatars: list[dict], final: str) -> tuple[Table, Table]:
    table = Table("final_avatars", "Final-recipe avatars on their test frames, beside trivial baselines "
                  "(mean over seeds, 95 % CI)", AVATAR_COLUMNS + SEEDED_COLUMNS + ["split"],
                  "Baselines predict each test frame from the training frames alone (their mean; the last one; the "
                  "one nearest in fitted expression, jaw, neck and camera), composited into the same true mask. "
                  "face_detection_rate / landmark_nme / identity_similarity: dlib on the renders (NME against the "
                  "frame's tracked landmarks, outer-eye normalised). split: last_frames (INSTA protocol) or "
                  "held_out_clips (every frame of a clip the avatar never saw). colour_matched_gain: a diagnostic, "
                  "the head-region PSNR gain over the best baseline when every prediction (model and baselines "
                  "alike) first takes each test frame's mean colour: structure without a recording's overall "
                  "colour, which a clip never seen can have its own of.")
    for subject in sorted({a["subject"] for a in avatars if a["recipe"] == "final" and a["init"] == final}):
        runs = seeded_runs(avatars, subject, "final", final)
        if runs:
            table.add(**seeded_row(runs), split=runs[0]["eval"].get("split"))
    base = Table("final_avatar_baselines", "The same test frames, scored for each trivial baseline",
                 ["subject", "predictor", "psnr", "psnr_head", "psnr_head_colour", "ssim", "st_lpips",
                  "face_detection_rate", "landmark_nme", "identity_similarity"],
                 "Seed 0's avatar (the baselines do not depend on the seed). psnr_head_colour: head-region PSNR "
                 "with each frame's mean colour matched to the truth's first.")
    for a in avatars:
        if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a" and a["seed"] == 0:
            part = a["eval"]["all"]
            for name, scores in [("model", part["model"])] + sorted(part["baselines"].items()):
                base.add(subject=a["subject"], predictor=name, **{k: scores.get(k) for k in base.columns[2:]})
    table.note += " " + not_beating(table, ("subject",))
    return table, base


def alpha_table(avatars: list[dict]) -> Table:
    table = Table("alpha1_vs_alpha2", "Avatars fine-tuned (base recipe) from alpha1 vs alpha2, all test frames and "
                  "the mouth-open subset (mean over seeds, 95 % CI)", AVATAR_COLUMNS + SEEDED_COLUMNS,
                  "The mouth-open subset = the test frames with the widest fitted jaw opening (the dissertation: 30 "
                  "per subject). alpha2 adds the mouth interior in its last pretraining phase.")
    for subject in sorted({a["subject"] for a in avatars if a["recipe"] == "base"}):
        for init in ("alpha1", "alpha2"):
            runs = seeded_runs(avatars, subject, "base", init)
            for part in ("all", "mouth_open") if runs else ():
                table.add(**seeded_row(runs, part))
    table.note += " " + not_beating(table, ("subject", "init", "subset"))
    return table


def alpha_paired_table(avatars: list[dict]) -> Table:
    """alpha2 - alpha1, paired by seed (same seed: same batches and offsets), with the verdict on the noise."""
    table = Table("alpha_paired", "alpha2 minus alpha1, paired by seed: is the difference larger than the "
                  "seed-to-seed noise?", ["subject", "subset", "metric", "seeds", "difference", "ci95", "verdict"],
                  "difference = mean over seeds of (alpha2 - alpha1) with the same seed; the verdict says whether its "
                  "95 % confidence interval (Student's t) excludes zero. Higher is better for PSNR and SSIM, lower "
                  "for ST-LPIPS.")
    for subject in sorted({a["subject"] for a in avatars if a["recipe"] == "base"}):
        one, two = (seeded_runs(avatars, subject, "base", i) for i in ("alpha1", "alpha2"))
        if not one or not two:
            continue
        for part in ("all", "mouth_open"):
            for metric in ("psnr", "ssim", "st_lpips"):
                a = {r["seed"]: r["eval"][part]["model"].get(metric) for r in one}
                b = {r["seed"]: r["eval"][part]["model"].get(metric) for r in two}
                if any(v is None for v in (*a.values(), *b.values())):
                    continue
                d = paired_difference(a, b)
                table.add(subject=subject, subset=part, metric=metric, seeds=d["n"], difference=d["mean"],
                          ci95=d["ci95"], verdict=d["verdict"])
    return table


def beta_table(avatars: list[dict]) -> Table:
    sd, dof = seed_noise(avatars)
    threshold = single_run_threshold(sd)
    table = Table("beta_ablation", "Avatars fine-tuned (base recipe) from beta1-beta6 continued from alpha1 / alpha2 "
                  "(dissertation figures 39-42)",
                  AVATAR_COLUMNS + ["mouth_open_psnr", "below_best_db", "differs_from_best"],
                  "beta1: real only; beta2: + z-augmentation; beta3: p=0.25; beta4: p 0.25->0; beta5: beta3 + z-aug; "
                  "beta6: beta4 + z-aug (the final recipe, from alpha2). One seed each: below_best_db = the best "
                  "beta's PSNR (same subject) minus this row's; differs_from_best says whether that exceeds the "
                  "seed-to-seed noise, 1.96 x sqrt(2) x the pooled seed-to-seed SD of test PSNR measured on the "
                  + (f"seeded avatars ({sd:.3f} dB, {dof} degrees of freedom: threshold {threshold:.2f} dB)."
                     if sd is not None else "seeded avatars (none here: no verdict)."))
    betas = [a for a in avatars if a["recipe"] == "base" and "_from_" in a["init"] and a["variant"] == "a"
             and a["seed"] == 0]
    ablated = {s for s in {a["subject"] for a in betas} if sum(a["subject"] == s for a in betas) > 1}
    best = {s: max(a["eval"]["all"]["model"]["psnr"] for a in betas if a["subject"] == s) for s in ablated}
    for a in sorted(betas, key=lambda r: (r["subject"], r["init"].split("_from_")[-1], r["init"])):
        if a["subject"] in ablated:  # subjects with the beta ablation (not a lone avatar of another experiment)
            below = best[a["subject"]] - a["eval"]["all"]["model"]["psnr"]
            differs = None if threshold is None else ("yes" if below > threshold else "no (within noise)")
            table.add(**avatar_row(a), mouth_open_psnr=a["eval"]["mouth_open"]["model"]["psnr"], below_best_db=below,
                      differs_from_best=differs)
    table.note += " " + not_beating(table, ("subject", "init"))
    return table


#: the stage-2 comparisons of figures 44-47: (label, treated, control) per alpha family
STAGE2_PAIRS = [("z-augmentation (beta2 vs beta1)", "beta2", "beta1"),
                ("z-augmentation (beta5 vs beta3)", "beta5", "beta3"),
                ("z-augmentation (beta6 vs beta4)", "beta6", "beta4"),
                ("synthetic share 0.25 (beta3 vs beta1)", "beta3", "beta1"),
                ("decaying share 0.25->0 (beta4 vs beta1)", "beta4", "beta1"),
                ("decaying vs constant share (beta4 vs beta3)", "beta4", "beta3"),
                ("continuing on real images (beta1 vs its alpha)", "beta1", "alpha")]


def stage2_table(avatars: list[dict]) -> Table:
    """Figures 44-47's pairs (z-augmentation, the schedule, continuing on real images) as differences of test PSNR
    on all and mouth-open frames, each with the verdict against the seed-to-seed noise."""
    sd, _ = seed_noise(avatars)
    threshold = single_run_threshold(sd)
    table = Table("stage2_comparisons", "Stage-2 comparisons (dissertation figures 44-47): treated minus control, "
                  "avatars fine-tuned with the base recipe", ["subject", "family", "comparison", "all_diff_db",
                                                              "mouth_open_diff_db", "verdict"],
                  "One seed per model: a difference counts only above " +
                  (f"{threshold:.2f} dB (1.96 x sqrt(2) x the pooled seed-to-seed SD)." if threshold is not None
                   else "the seed noise, which this run did not measure (no verdict)."))
    runs = {(a["subject"], a["init"]): a["eval"] for a in avatars
            if a["recipe"] == "base" and a["variant"] == "a" and a["seed"] == 0}
    for subject in sorted({s for s, _ in runs}):
        for alpha in ("alpha1", "alpha2"):
            for label, treated, control in STAGE2_PAIRS:
                t_name = f"{treated}_from_{alpha}"
                c_name = alpha if control == "alpha" else f"{control}_from_{alpha}"
                if (subject, t_name) not in runs or (subject, c_name) not in runs:
                    continue
                t, c = runs[(subject, t_name)], runs[(subject, c_name)]
                diff = t["all"]["model"]["psnr"] - c["all"]["model"]["psnr"]
                mouth = t["mouth_open"]["model"]["psnr"] - c["mouth_open"]["model"]["psnr"]
                verdict = (None if threshold is None else
                           "within noise" if abs(diff) <= threshold else ("better" if diff > 0 else "worse"))
                table.add(subject=subject, family=alpha, comparison=label, all_diff_db=diff, mouth_open_diff_db=mouth,
                          verdict=verdict)
    return table


def interp_table(avatars: list[dict], final: str) -> Table:
    table = Table("interpolation", "Interpolation experiment (dissertation figure 54): (a) all frames, (b) every "
                  "second frame dropped, (c) (b) + interpolated frames (base recipe)",
                  AVATAR_COLUMNS + ["gain_c_over_b_db"],
                  f"Published: (c) is {PUBLISHED_INTERP_GAIN_DB} dB PSNR above (b). Variant (c)'s new frames come from "
                  "the XVFI-style network; their parameters are the neighbours' mean (no fit of the new frame).")
    by_subject: dict[str, dict] = {}
    for a in avatars:
        if a["recipe"] == "base" and a["init"] == final and a["seed"] == 0:
            by_subject.setdefault(a["subject"], {})[a["variant"]] = a
    for subject, variants in sorted(by_subject.items()):
        if not ({"b", "c"} & set(variants)):
            continue
        gain = None
        if "b" in variants and "c" in variants:
            gain = variants["c"]["eval"]["all"]["model"]["psnr"] - variants["b"]["eval"]["all"]["model"]["psnr"]
        for v in ("a", "b", "c"):
            if v in variants:
                table.add(**avatar_row(variants[v]), gain_c_over_b_db=gain if v == "c" else None)
    table.note += " " + not_beating(table, ("subject", "variant"))
    return table


def comparison_table(avatars: list[dict], final: str, scale: str) -> Table:
    table = Table("table2_comparison", "Table 2: published methods (dissertation) beside this run",
                  ["source", "method", "data", "psnr", "ssim", "lpips", "st_lpips", "best_baseline_psnr",
                   "creation_time"],
                  "Rows marked 'published' are copied from the dissertation (INSTA videos, 256x256, RTX 4090); rows "
                  f"marked 'this run' come from this workflow at scale '{scale}' on the data named, on CPU, each "
                  "beside what its best trivial baseline scores on the same frames. They are not the same data or "
                  "budget and are shown side by side only as labelled. LPIPS of this run is LPIPS-VGG where its "
                  "backbone was given, else missing; ST-LPIPS is another metric (shift-tolerant, AlexNet).")
    for row in PUBLISHED_TABLE2:
        table.add(source="published", data="INSTA, 256x256", **row)
    for a in avatars:
        if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a" and a["seed"] == 0:
            m, g = a["eval"]["all"]["model"], a["eval"]["all"]["gain"]["psnr"]
            table.add(source="this run", method=f"avatarlab ({final})", data=f"{a['subject']}, {scale}",
                      psnr=m["psnr"], ssim=m["ssim"], lpips=m.get("lpips"), st_lpips=m.get("st_lpips"),
                      best_baseline_psnr=f"{g['baseline']:.2f} ({g['best_baseline']})",
                      creation_time=f"{a['train']['train_seconds']:.0f} s fine-tuning (CPU)")
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


REAL_SPEECH_ROWS = {"synthetic": "trained on the synthetic corpus", "adapted_other_clips":
                    "+ fine-tuned on the other real clips (leave one clip out)", "adapted_other_speakers":
                    "+ fine-tuned on the other speakers' clips only"}
SPEECH_MODELS = {"lstm_reg": "seed 000, with regularisation", "lstm_noreg": "seed 000, without regularisation",
                 "window": "seed 001 sliding window (phoneme labels in, as the paper's linguistic indicators)"}


def real_speech_rows(results: Path):
    """(method label, speaker, row) of speech/real_eval.json: per model and speaker, as trained, then adapted."""
    real = read_json(results / "speech" / "real_eval.json")
    for name, model in (real or {}).get("models", {}).items():
        for speaker, by_row in model["speakers"].items():
            for key in [k for k in REAL_SPEECH_ROWS if k in by_row]:
                yield f"{SPEECH_MODELS.get(name, name)}, {REAL_SPEECH_ROWS[key]}", speaker, by_row[key]


def speech_table(results: Path, scale: str) -> Table:
    table = Table("speech", "Speech-driven animation (seed 000's table; seed 001's window model)",
                  ["source", "method", "data", "latency_ms", "lip_error_iod", "motion_error_iod", "best_baseline",
                   "baseline_iod", "gain_iod", "clip_gain_ci95", "wins", "fine_tuning_seeds", "compute_ms_per_step",
                   "real_time_factor", "train_seconds"],
                  "lip_error_iod: mean lip-landmark error / outer-eye distance, in percent (the published values "
                  "are read as percent too). Published rows: GRID (34 speakers, 24/6/4 split). 'this run' rows: the "
                  f"synthetic espeak-ng corpus at scale '{scale}', test speakers unseen in training; the window model "
                  "(seed 001) is given the true phoneme labels, the others only audio. motion_error_iod: the same "
                  "after moving each utterance's prediction to the speaker's mean shape (no model here is told the "
                  "speaker's face; the raw error mixes that in). Baselines, on the motion error of the same test "
                  "frames: still_mouth (each utterance at its own mean shape) and, for the model given phonemes, "
                  "phoneme_mean (that mean plus the training frames' mean offset for the frame's true phoneme); "
                  "gain_iod = baseline - model (> 0: the model is better). Real-clip rows (speech/real_eval.py): dlib's "
                  "landmarks of GRID and Obama clips as truth, motion only (each clip's identity offset removed), "
                  "the audio models as trained and fine-tuned on the real clips' own audio with the scored clip (or "
                  "its whole speaker) left out; clip_gain_ci95: the 95 % CI half-width of the per-clip paired gain "
                  "over the still mouth, wins: clips where the model beats it. A gain is one only when it exceeds "
                  "its CI. fine_tuning_seeds: the fine-tuned rows' per-clip mean gain over the still mouth (the "
                  "gain clip_gain_ci95 belongs to) in every fine-tuning seed (speech.adapt_seeds; the row is the "
                  "first), and in how many seeds it exceeds its CI.")
    for row in PUBLISHED_SPEECH:
        table.add(source="published", data="GRID", **row)
    for key, label in SPEECH_MODELS.items():
        run = read_json(results / "speech" / key / "metrics.json")
        if run:
            t = run["test"]
            best = t.get("best_baseline")
            table.add(source="this run", method=label, data=f"synthetic corpus, {scale}", latency_ms=t["latency_ms"],
                      lip_error_iod=t["lip_error_percent"], motion_error_iod=t.get("motion_lip_error_percent"),
                      best_baseline=best,
                      baseline_iod=t["baselines"][best] if best else None, gain_iod=t.get("gain_over_best_baseline"),
                      compute_ms_per_step=t.get("compute_ms_per_step"),
                      real_time_factor=t.get("real_time_factor"), train_seconds=run["train_seconds"])
    window = read_json(results / "speech" / "window" / "metrics.json")
    if window and window["test"].get("retargeted_lip_error_percent") is not None:
        table.add(source="this run", method="  seed 001 retargeted to the head model's rig (+-3 sigma poses), "
                  "motion only (identity offset removed)", data=f"synthetic corpus, {scale}",
                  lip_error_iod=window["test"]["retargeted_lip_error_percent"])
    for method, speaker, r in real_speech_rows(results):
        table.add(source="this run", method=method, data=f"{r['clips']} real {speaker} clips",
                  motion_error_iod=r["lip_error_percent"], best_baseline="still_mouth",
                  baseline_iod=r["still_mouth_percent"], gain_iod=r["still_mouth_percent"] - r["lip_error_percent"],
                  clip_gain_ci95=r["gain_ci95"], wins=f"{r['wins']}/{r['clips']}",
                  fine_tuning_seeds=seed_spread_text(r.get("fine_tuning_seeds")))
    return table


def seed_spread_text(spread: dict | None) -> str | None:
    """'+0.04 to +0.10 over 3 seeds, 0 beyond the CI' for a fine-tuned real-clip row (None for one seed)."""
    if not spread:
        return None
    return (f"{signed_range(spread['gain_mean_per_clip'])} over {spread['seeds']} seeds, "
            f"{spread['beats_still_mouth']} beyond the CI")


def speech_timing_table(results: Path) -> Table:
    """The real-clip rows again, on the mouth opening's timing alone (speech/real_eval.py `opening_timing`)."""
    table = Table("speech_opening_timing", "Speech on real clips: does the predicted mouth open when the real one does?",
                  ["method", "data", "opening_r", "best_baseline", "baseline_r", "gain_r", "clip_gain_ci95", "wins",
                   "verdict"],
                  "opening_r: Pearson's r over each clip's frames between the predicted and the true (dlib) mouth "
                  "opening, the inner lips' gap, averaged over clips. A still mouth follows nothing (r = 0); the "
                  "trivial predictor from the audio alone is its loudness (log RMS over the video frame's own 40 ms: "
                  "loudness_frame, or over the model's own input window: loudness_window), and best_baseline is the "
                  "better of the two on these clips. gain_r: the per-clip paired gain over it, clip_gain_ci95 its "
                  "95 % CI half-width over clips; verdict 'better' / 'worse' only beyond that CI.")
    for method, speaker, r in real_speech_rows(results):
        t = r.get("opening_timing")
        if not t:
            continue
        half, gain = t["gain_ci95"], t["gain_mean_per_clip"]
        verdict = gain_verdict(gain, half, "clips'") or "missing"
        table.add(method=method, data=f"{r['clips']} real {speaker} clips", opening_r=t["model_r"],
                  best_baseline=t["best_baseline"], baseline_r=t["baselines_r"][t["best_baseline"]], gain_r=gain,
                  clip_gain_ci95=half, wins=f"{t['wins']}/{r['clips']}", verdict=verdict)
    return table


def save_figure(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


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
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8))
    for a in finals:
        curve = [pt for pt in a["eval"].get("curve", []) if pt.get("seconds") is not None]
        base = a["eval"]["all"]["baselines"]
        for ax, metric in zip(axes, ("psnr", "ssim")):
            if curve:
                ax.plot([pt["seconds"] for pt in curve], [pt[metric] for pt in curve], "o-", ms=3,
                        color=colours[a["subject"]], label=f"{a['subject']} (final recipe)")
            best = max(base.values(), key=lambda b: b[metric])[metric]
            ax.axhline(best, ls="--", lw=1, color=colours[a["subject"]], alpha=0.7)
    for ax, label in zip(axes, ("test PSNR (dB)", "test SSIM")):
        ax.set_xlabel("fine-tuning time on this CPU (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7)
    fig.suptitle("quality vs creation time (dashed: each subject's best trivial baseline on the same frames)",
                 fontsize=9)
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


#: what the report step writes into its folder (the folder also holds other steps' files: the renderer experiment)
REPORT_PARTS = ("tables", "figures", "README.md", "summary.json")


def build(results: Path, out: Path, final: str, scale: str) -> dict:
    """Writes the report into a staging folder beside `out`, then moves each part into place (summary.json last): an
    interrupted report leaves the previous one whole."""
    staging = out.parent / f".{out.name}.staging"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    summary = write_report(results, staging, final, scale)
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


def write_report(results: Path, out: Path, final: str, scale: str) -> dict:
    tables_dir, figures_dir = out / "tables", out / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    avatars = load_avatars(results)
    finals, final_baselines = final_avatar_table(avatars, final)
    tables = [preprocessing_table(results), pretraining_table(results), controls_table(results),
              renderer_table(results), finals,
              final_baselines, alpha_table(avatars), alpha_paired_table(avatars), beta_table(avatars),
              stage2_table(avatars), interp_table(avatars, final),
              comparison_table(avatars, final, scale), claims_table(results, avatars, final, scale),
              applications_table(results), speech_table(results, scale), speech_timing_table(results),
              substitutions_table()]
    for table in tables:
        table.write(tables_dir)
    figures = quality_figures(avatars, final, figures_dir) if avatars else []
    for a in avatars:
        if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a" and a["seed"] == 0:
            figures.append(copy_figure(a["dir"] / "test_frames.png", figures_dir / f"test_frames_{a['subject']}.png"))
    for path in sorted(results.glob("apps/*/*.png")):
        figures.append(copy_figure(path, figures_dir / f"{path.parent.name}_{path.name}"))
    for path in sorted(results.glob("speech/speak_*.png")):
        figures.append(copy_figure(path, figures_dir / path.name))
    for name in ("alpha1", "alpha2", final):
        figures.append(copy_figure(results / "pretrain" / name / "eval_samples.png",
                                   figures_dir / f"pretrained_{name}_held_out.png"))
    for path in sorted(results.glob("pretrain/controls/*.png")):
        figures.append(copy_figure(path, figures_dir / f"pretrained_controls_{path.name}"))
    figures += [copy_figure(results / "headmodel" / "render_grid.png", figures_dir / "head_model_sweeps.png"),
                copy_figure(results / "report" / "renderer_experiment.png", figures_dir / "renderer_experiment.png")]
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
    summary = build(Path(rep.results_dir), Path(rep.out_dir), str(rep.final_recipe), cfg.report.scale)
    log.info("report: %d avatars, tables %s, %d figures -> %s", summary["avatars"], summary["rows"],
             len(summary["figures"]), rep.out_dir)


if __name__ == "__main__":
    main()
