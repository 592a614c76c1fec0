"""The report's speech tables: seed 000's table beside this run's models on the synthetic corpus and on real clips,
and the real clips' mouth-opening timing."""
from __future__ import annotations

from avatarlab.metrics.seeds import gain_verdict, signed_range
from avatarlab.report.published import PUBLISHED_SPEECH
from avatarlab.report.table import Table
from avatarlab.workflow.layout import ResultsTree

REAL_SPEECH_ROWS = {"synthetic": "trained on the synthetic corpus", "adapted_other_clips":
                    "+ fine-tuned on the other real clips (leave one clip out)", "adapted_other_speakers":
                    "+ fine-tuned on the other speakers' clips only"}


SPEECH_MODELS = {"lstm_reg": "seed 000, with regularisation", "lstm_noreg": "seed 000, without regularisation",
                 "window": "seed 001 sliding window (phoneme labels in, as the paper's linguistic indicators)"}


def real_speech_rows(tree: ResultsTree):
    """(method label, speaker, row) of speech/real_eval.json: per model and speaker, as trained, then adapted."""
    real = tree.load(tree.speech("real_eval.json"))
    for name, model in (real or {}).get("models", {}).items():
        for speaker, by_row in model["speakers"].items():
            for key in [k for k in REAL_SPEECH_ROWS if k in by_row]:
                yield f"{SPEECH_MODELS.get(name, name)}, {REAL_SPEECH_ROWS[key]}", speaker, by_row[key]


def speech_table(tree: ResultsTree, scale: str) -> Table:
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
                  "first), and in how many seeds it exceeds its CI.",
                  shown=["source", "method", "data", "motion_error_iod", "best_baseline", "baseline_iod", "gain_iod",
                         "wins"],
                  ci_columns={"gain_iod": "clip_gain_ci95"})
    for row in PUBLISHED_SPEECH:
        table.add(source="published", data="GRID", **row)
    for key, label in SPEECH_MODELS.items():
        run = tree.load(tree.speech(key, "metrics.json"))
        if run:
            t = run["test"]
            best = t.get("best_baseline")
            table.add(source="this run", method=label, data=f"synthetic corpus, {scale}", latency_ms=t["latency_ms"],
                      lip_error_iod=t["lip_error_percent"], motion_error_iod=t.get("motion_lip_error_percent"),
                      best_baseline=best,
                      baseline_iod=t["baselines"][best] if best else None, gain_iod=t.get("gain_over_best_baseline"),
                      compute_ms_per_step=t.get("compute_ms_per_step"),
                      real_time_factor=t.get("real_time_factor"), train_seconds=run["train_seconds"])
    window = tree.load(tree.speech("window", "metrics.json"))
    if window and window["test"].get("retargeted_lip_error_percent") is not None:
        table.add(source="this run", method="  seed 001 retargeted to the head model's rig (+-3 sigma poses), "
                  "motion only (identity offset removed)", data=f"synthetic corpus, {scale}",
                  lip_error_iod=window["test"]["retargeted_lip_error_percent"])
    for method, speaker, r in real_speech_rows(tree):
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


def speech_timing_table(tree: ResultsTree) -> Table:
    """The real-clip rows again, on the mouth opening's timing alone (speech/real_eval.py `opening_timing`)."""
    table = Table("speech_opening_timing", "Speech on real clips: does the predicted mouth open when the real one does?",
                  ["method", "data", "opening_r", "best_baseline", "baseline_r", "gain_r", "clip_gain_ci95", "wins",
                   "verdict"],
                  "opening_r: Pearson's r over each clip's frames between the predicted and the true (dlib) mouth "
                  "opening, the inner lips' gap, averaged over clips. A still mouth follows nothing (r = 0); the "
                  "trivial predictor from the audio alone is its loudness (log RMS over the video frame's own 40 ms: "
                  "loudness_frame, or over the model's own input window: loudness_window), and best_baseline is the "
                  "better of the two on these clips. gain_r: the per-clip paired gain over it, clip_gain_ci95 its "
                  "95 % CI half-width over clips; verdict 'better' / 'worse' only beyond that CI.",
                  shown=["method", "data", "opening_r", "best_baseline", "baseline_r", "gain_r", "wins", "verdict"],
                  ci_columns={"gain_r": "clip_gain_ci95"})
    for method, speaker, r in real_speech_rows(tree):
        t = r.get("opening_timing")
        if not t:
            continue
        half, gain = t["gain_ci95"], t["gain_mean_per_clip"]
        verdict = gain_verdict(gain, half, "clips'") or "missing"
        table.add(method=method, data=f"{r['clips']} real {speaker} clips", opening_r=t["model_r"],
                  best_baseline=t["best_baseline"], baseline_r=t["baselines_r"][t["best_baseline"]], gain_r=gain,
                  clip_gain_ci95=half, wins=f"{t['wins']}/{r['clips']}", verdict=verdict)
    return table
