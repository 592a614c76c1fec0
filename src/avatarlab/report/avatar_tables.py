"""The report's avatar tables: the final avatars over seeds with CIs, alpha1 vs alpha2 (also paired by seed), the
beta ablation and the stage-2 pairs with their noise verdicts, the interpolation experiment, and table 2 beside the
published rows."""
from __future__ import annotations

from avatarlab.metrics.seeds import mean_ci, paired_difference, single_run_threshold
from avatarlab.report.claims import PUBLISHED_INTERP_GAIN_DB
from avatarlab.report.published import PUBLISHED_TABLE2
from avatarlab.report.runs import seed_noise, seeded_runs
from avatarlab.report.table import Headline, Table, gain_columns, not_beating

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


def final_seeds(avatars: list[dict], final: str):
    """(subject, its final avatars' runs over seeds, their test scores, the baselines' test scores) per subject."""
    for subject in sorted({a["subject"] for a in avatars if a["recipe"] == "final" and a["init"] == final}):
        runs = seeded_runs(avatars, subject, "final", final)
        if runs:
            yield subject, runs, [a["eval"]["all"]["model"] for a in runs], runs[0]["eval"]["all"]["baselines"]


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
                  "colour, which a clip never seen can have its own of.",
                  shown=["subject", "seeds", "test_frames", "psnr", "baseline_psnr", "gain", "ssim", "st_lpips"],
                  headline=Headline("psnr", ("subject",), each=True))
    for _, runs, _, _ in final_seeds(avatars, final):
        table.add(**seeded_row(runs), split=runs[0]["eval"].get("split"))
    base = Table("final_avatar_baselines", "The same test frames, scored for each trivial baseline",
                 ["subject", "predictor", "psnr", "psnr_head", "psnr_head_colour", "ssim", "st_lpips",
                  "face_detection_rate", "landmark_nme", "identity_similarity"],
                 "Seed 0's avatar (the baselines do not depend on the seed). psnr_head_colour: head-region PSNR "
                 "with each frame's mean colour matched to the truth's first.",
                 shown=["subject", "predictor", "psnr", "psnr_head", "ssim", "st_lpips", "face_detection_rate",
                        "identity_similarity"])
    for a in avatars:
        if a["recipe"] == "final" and a["init"] == final and a["variant"] == "a" and a["seed"] == 0:
            part = a["eval"]["all"]
            for name, scores in [("model", part["model"])] + sorted(part["baselines"].items()):
                base.add(subject=a["subject"], predictor=name, **{k: scores.get(k) for k in base.columns[2:]})
    table.note += " " + not_beating(table, ("subject",))
    return table, base


def sharpness_table(avatars: list[dict], final: str) -> Table:
    """The final avatars beside a copied training frame, every seed: ST-LPIPS against the nearest training frame's
    (gain = nearest - avatar, > 0: the avatar is closer to the truth in texture)."""
    table = Table("final_avatar_sharpness", "Final-recipe avatars beside a copied training frame: ST-LPIPS (lower is "
                  "closer; mean over seeds, 95 % CI)",
                  ["subject", "seeds", "st_lpips", "st_lpips_ci95", "nearest_st_lpips", "gain", "gain_ci95",
                   "seeds_below_nearest"],
                  "The same test frames as the table above. nearest_*: the training frame nearest in fitted "
                  "expression, jaw, neck and camera, copied (the baselines do not depend on the seed); gain: its "
                  "ST-LPIPS minus the avatar's, with the 95 % CI over seeds; seeds_below_nearest: the seeds whose "
                  "avatar scores below it. ST-LPIPS may also train the avatar (finetune.w_st_lpips): the next table "
                  "scores the renders with dlib, which does not.",
                  headline=Headline("gain", ("subject",), baseline=None, each=True,
                                    versus="the nearest training frame in ST-LPIPS"))
    for subject, runs, models, bases in final_seeds(avatars, final):
        nearest = (bases.get("nearest") or {}).get("st_lpips")
        if nearest is None or any(m.get("st_lpips") is None for m in models):
            continue
        row = {"subject": subject, "seeds": len(runs), "nearest_st_lpips": nearest,
               "seeds_below_nearest": f"{sum(m['st_lpips'] < nearest for m in models)} of {len(runs)}"}
        row["st_lpips"], row["st_lpips_ci95"], _ = mean_ci(m["st_lpips"] for m in models)
        row["gain"], row["gain_ci95"], _ = mean_ci(nearest - m["st_lpips"] for m in models)
        table.add(**row)
    return table


def face_table(avatars: list[dict], final: str) -> Table:
    """The final avatars as faces, judged by dlib (never trained with them): the detection rate on the renders, the
    68-point landmark error (NME) and the identity similarity, each beside the mean and the nearest training frame's
    (nme_gain = nearest - avatar, > 0: the avatar's features lie closer to the truth's)."""
    table = Table("final_avatar_faces", "Final-recipe avatars as faces: dlib's landmark error (NME, lower is better) "
                  "and identity similarity beside the copied frames' (mean over seeds, 95 % CI)",
                  ["subject", "seeds", "face_detection_rate", "landmark_nme", "landmark_nme_ci95", "mean_frame_nme",
                   "nearest_nme", "nme_gain", "nme_gain_ci95", "identity_similarity", "identity_similarity_ci95",
                   "mean_frame_identity", "nearest_identity"],
                  "The same test frames. face_detection_rate: the share of renders where dlib finds a face; "
                  "landmark_nme: its 68 points against the frame's tracked landmarks, outer-eye normalised, over the "
                  "renders where a face is found; identity_similarity: the cosine of dlib's face descriptors of "
                  "render and truth. A sharp render with its features in the wrong place scores a low ST-LPIPS "
                  "(shift-tolerant) but a high NME.",
                  shown=["subject", "face_detection_rate", "landmark_nme", "mean_frame_nme", "nearest_nme",
                         "identity_similarity", "mean_frame_identity", "nearest_identity"],
                  headline=Headline("nme_gain", ("subject",), gain="nme_gain", gain_ci="nme_gain_ci95",
                                    baseline=None, each=True, versus="the nearest training frame in landmark error"))
    for subject, runs, models, bases in final_seeds(avatars, final):
        detection = mean_ci(m.get("face_detection_rate") for m in models)[0]
        if detection is None:  # dlib was not run on this subject's renders
            continue
        mean_frame, nearest = bases.get("mean_frame") or {}, bases.get("nearest") or {}
        row = {"subject": subject, "seeds": len(runs), "face_detection_rate": detection,
               "mean_frame_nme": mean_frame.get("landmark_nme"), "nearest_nme": nearest.get("landmark_nme"),
               "mean_frame_identity": mean_frame.get("identity_similarity"),
               "nearest_identity": nearest.get("identity_similarity")}
        row["landmark_nme"], row["landmark_nme_ci95"], _ = mean_ci(m.get("landmark_nme") for m in models)
        if row["nearest_nme"] is not None:
            row["nme_gain"], row["nme_gain_ci95"], _ = mean_ci(
                row["nearest_nme"] - m["landmark_nme"] for m in models if m.get("landmark_nme") is not None)
        row["identity_similarity"], row["identity_similarity_ci95"], _ = mean_ci(
            m.get("identity_similarity") for m in models)
        table.add(**row)
    return table


def fit_table(avatars: list[dict], final: str) -> Table:
    """The final avatars on frames they trained on beside their test frames (eval.json's `trained`): a test score
    far below the training frames' is a model that fits what it saw and does not carry it to new frames; a low
    score on both, one that does not fit. gap = trained - test, with its 95 % CI over seeds."""
    table = Table("final_avatar_fit", "Final-recipe avatars on frames they trained on, beside their test frames "
                  "(mean over seeds, 95 % CI)",
                  ["subject", "seeds", "trained_frames", "trained_psnr", "psnr", "gap_psnr", "gap_psnr_ci95",
                   "trained_ssim", "ssim", "gap_ssim", "gap_ssim_ci95", "trained_st_lpips", "st_lpips"],
                  "trained_*: the avatar rendered, as each test frame is, from the fitted codes of evenly spaced "
                  "training frames (without the per-frame offsets it learned for them); the other columns: the test "
                  "frames, as above. gap_*: trained minus test. A test target above the trained frames' score is "
                  "out of the model's reach by generalisation alone.",
                  shown=["subject", "trained_frames", "trained_psnr", "psnr", "gap_psnr", "trained_ssim", "ssim",
                         "trained_st_lpips"])
    for subject, runs, models, _ in final_seeds(avatars, final):
        fits = [(a["eval"].get("trained") or {}).get("model") for a in runs]
        if any(f is None for f in fits):
            continue  # evaluated without trained frames (evaluate.trained_frames = 0) or before they were scored
        row = {"subject": subject, "seeds": len(runs), "trained_frames": runs[0]["eval"]["trained"]["frames"]}
        for key in ("psnr", "ssim", "st_lpips"):
            row[f"trained_{key}"] = mean_ci(f.get(key) for f in fits)[0]
            row[key] = mean_ci(m.get(key) for m in models)[0]
        for key in ("psnr", "ssim"):
            row[f"gap_{key}"], row[f"gap_{key}_ci95"], _ = mean_ci(f[key] - m[key] for f, m in zip(fits, models))
        table.add(**row)
    return table


def same_recording_table(avatars: list[dict], final: str) -> Table:
    """The final avatars on the last frames of the recordings they trained on (eval.json's `same_recording`, subjects
    with held-out clips and `finetune.recording_test_frames`): the INSTA protocol's kind of test frame, beside the
    held-out clips' new recordings, each beside its own baselines."""
    table = Table("final_avatar_same_recording", "Final-recipe avatars on later frames of the recordings they trained "
                  "on, beside their unseen recordings (mean over seeds, 95 % CI)",
                  ["subject", "seeds", "test_frames", "psnr", "best_baseline", "baseline_psnr", "gain", "gain_ci95",
                   "ssim", "st_lpips", "nearest_st_lpips", "landmark_nme", "identity_similarity",
                   "nearest_identity", "unseen_recordings_psnr", "unseen_recordings_ssim"],
                  "test_frames: the last frames of every training clip, held out of training and of the identity fit "
                  "(finetune.recording_test_frames), so a later moment of a recording the avatar trained on, as in "
                  "the dissertation's protocol (the last frames of one video); scored as the test frames are, beside "
                  "the baselines from the frames the avatar saw. unseen_recordings_*: the held-out clips' scores "
                  "(the tables above). A subject tested on its own last frames (synthetic) has no row.",
                  shown=["subject", "test_frames", "psnr", "baseline_psnr", "gain", "ssim", "st_lpips",
                         "nearest_st_lpips"],
                  headline=Headline("psnr", ("subject",), each=True))
    for subject, runs, models, _ in final_seeds(avatars, final):
        if any(a["eval"].get("same_recording") is None for a in runs):
            continue
        row = seeded_row(runs, "same_recording")
        bases = runs[0]["eval"]["same_recording"]["baselines"]
        table.add(subject=subject, seeds=len(runs), test_frames=row["test_frames"], psnr=row["psnr"],
                  best_baseline=row["best_baseline"], baseline_psnr=row["baseline_psnr"], gain=row["gain"],
                  gain_ci95=row["gain_ci95"], ssim=row["ssim"], st_lpips=row["st_lpips"],
                  nearest_st_lpips=(bases.get("nearest") or {}).get("st_lpips"), landmark_nme=row["landmark_nme"],
                  identity_similarity=row["identity_similarity"],
                  nearest_identity=(bases.get("nearest") or {}).get("identity_similarity"),
                  unseen_recordings_psnr=mean_ci(m["psnr"] for m in models)[0],
                  unseen_recordings_ssim=mean_ci(m["ssim"] for m in models)[0])
    return table


def alpha_table(avatars: list[dict]) -> Table:
    table = Table("alpha1_vs_alpha2", "Avatars fine-tuned (base recipe) from alpha1 vs alpha2, all test frames and "
                  "the mouth-open subset (mean over seeds, 95 % CI)", AVATAR_COLUMNS + SEEDED_COLUMNS,
                  "The mouth-open subset = the test frames with the widest fitted jaw opening (the dissertation: 30 "
                  "per subject). alpha2 adds the mouth interior in its last pretraining phase.",
                  shown=["subject", "init", "subset", "seeds", "psnr", "gain", "ssim", "st_lpips"],
                  headline=Headline("psnr", ("subject", "init", "subset"), each=True))
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
                  "for ST-LPIPS.", ci_columns={"difference": "ci95"})
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
                     if sd is not None else "seeded avatars (none here: no verdict)."),
                  shown=["subject", "init", "psnr", "gain", "mouth_open_psnr", "below_best_db", "differs_from_best",
                         "st_lpips"],
                  headline=Headline("psnr", ("subject", "init"), gain_ci=None))
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
                  "the XVFI-style network; their parameters are the neighbours' mean (no fit of the new frame).",
                  shown=["subject", "variant", "test_frames", "psnr", "best_baseline", "gain", "gain_c_over_b_db",
                         "st_lpips"],
                  headline=Headline("psnr", ("subject", "variant"), gain_ci=None, each=True))
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
