"""Landmark normalisation and the lip error of seeds 000/001: frames similarity-aligned to a reference on the stable
points (Procrustes with Kabsch rotation), lip error in percent of the inter-ocular distance."""
from __future__ import annotations

import numpy as np

from avatarlab.metrics.alignment import similarity_transform

STABLE = list(range(17, 48))  # brows, nose, eyes
LIPS = list(range(48, 68))


def align_to(points: np.ndarray, reference: np.ndarray, idx=STABLE) -> np.ndarray:
    """Similarity-align each (68, 2) frame of `points` (T, 68, 2) to `reference` on `idx` (Umeyama / Kabsch)."""
    out = np.empty_like(points)
    for t, frame in enumerate(points):
        scale, rotation, shift = similarity_transform(frame[idx], reference[idx])
        out[t] = scale * frame @ rotation.T + shift
    return out


def lip_error_percent(pred: np.ndarray, truth: np.ndarray) -> float:
    iod = np.linalg.norm(truth[:, 36] - truth[:, 45], axis=1)
    err = np.linalg.norm(pred[:, LIPS] - truth[:, LIPS], axis=2).mean(1) / iod
    return float(100 * err.mean())


def mouth_opening(points: np.ndarray) -> np.ndarray:
    """The gap between the inner lips' middle points (62 above, 66 below; y up) of each (68, 2) frame of (T, 68, 2)
    aligned landmarks: the mouth's opening, whose timing a model of speech should follow."""
    return points[:, 62, 1] - points[:, 66, 1]


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson's r of two series; 0 when either is constant (a still mouth follows nothing)."""
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    a, b = a.astype(np.float64) - a.mean(dtype=np.float64), b.astype(np.float64) - b.mean(dtype=np.float64)
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def motion_only(preds: list[np.ndarray], truths: list[np.ndarray]) -> np.ndarray:
    """Each utterance's predicted frames moved so that their mean shape is the truth's (the speaker's face, which
    no model here is told): the lip error of what remains is the error of the mouth's motion."""
    return np.concatenate([p - p.mean(0, keepdims=True) + t.mean(0, keepdims=True) for p, t in zip(preds, truths)])


def trivial_predictions(train: list[dict], test: list[dict]) -> dict[str, np.ndarray]:
    """What a model must beat, frame by frame on the test utterances (aligned landmarks, `labels` = phoneme ids):
    - still_mouth: every frame of an utterance at that utterance's own mean shape (a closed-loop baseline that even
      knows the speaker's face);
    - phoneme_mean: the utterance's mean shape plus the mean offset from their utterance's mean of the training frames
      with the same phoneme label (a lookup table that is given the true phoneme of every frame, as seed 001 is)."""
    sums, counts = {}, {}
    for item in train:
        offsets = item["landmarks"] - item["landmarks"].mean(0, keepdims=True)
        for label in np.unique(item["labels"]):
            at = item["labels"] == label
            sums[label] = sums.get(label, 0) + offsets[at].sum(0)
            counts[label] = counts.get(label, 0) + int(at.sum())
    still, lookup = [], []
    for item in test:
        mean = np.repeat(item["landmarks"].mean(0, keepdims=True), len(item["landmarks"]), 0)
        still.append(mean)
        lookup.append(mean + np.stack([sums[k] / counts[k] if k in counts else np.zeros((68, 2))
                                       for k in item["labels"]]))
    return {"still_mouth": still, "phoneme_mean": lookup}


def baseline_scores(train: list[dict], test: list[dict], model_error: float,
                    fair: tuple[str, ...] = ("still_mouth", "phoneme_mean")) -> dict:
    """The trivial predictors' motion lip errors (`motion_only`) on the same test frames, the best of the `fair`
    ones (those given no more than the model is) and the model's gain over it (positive: the model's motion error
    is that much lower, in percent of the inter-ocular distance)."""
    truths = [item["landmarks"] for item in test]
    truth = np.concatenate(truths)
    scores = {name: lip_error_percent(motion_only(pred, truths), truth)
              for name, pred in trivial_predictions(train, test).items()}
    best = min(fair, key=scores.get)
    return {"baselines": scores, "best_baseline": best, "gain_over_best_baseline": scores[best] - model_error}
