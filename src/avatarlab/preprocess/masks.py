"""Head masks (face, hair, neck; not background or clothes) without downloaded weights.

GrabCut seeded from the landmarks: the landmark hull is sure foreground; an ellipse grown upward from it (forehead and
hair) and a band below the chin (neck) are probable foreground; the image border and far regions are background.
Masks are then smoothed over time (a short window vote), and frames without landmarks take the nearest frame's
mask. Pluggable: `preprocess.mask.method` names the function in METHODS. Writes `masks.npz` and `masks.json`.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_json

log = logging.getLogger(__name__)
READS = ('seed', 'preprocess')  # the config sections this step reads (runtime/entry.py)


def seed_mask(shape, landmarks: np.ndarray) -> np.ndarray:
    """GrabCut initial labels from 68 landmarks."""
    h, w = shape
    labels = np.full((h, w), cv2.GC_BGD, np.uint8)
    pts = landmarks.astype(np.float32)
    jaw_w = np.linalg.norm(pts[16] - pts[0])
    brow_y = pts[17:27, 1].min()
    chin = pts[8]
    centre = np.array([(pts[0, 0] + pts[16, 0]) / 2, (brow_y + chin[1]) / 2 - 0.2 * jaw_w])
    axes = (int(0.78 * jaw_w), int(0.95 * (chin[1] - brow_y) + 0.35 * jaw_w))
    cv2.ellipse(labels, (int(centre[0]), int(centre[1])), axes, 0, 0, 360, cv2.GC_PR_BGD, -1)
    axes_in = (int(0.62 * jaw_w), int(0.8 * (chin[1] - brow_y) + 0.25 * jaw_w))
    cv2.ellipse(labels, (int(centre[0]), int(centre[1])), axes_in, 0, 0, 360, cv2.GC_PR_FGD, -1)
    neck_w = 0.32 * jaw_w
    cv2.rectangle(labels, (int(chin[0] - neck_w), int(chin[1] - 0.1 * jaw_w)),
                  (int(chin[0] + neck_w), int(chin[1] + 0.35 * jaw_w)), cv2.GC_PR_FGD, -1)
    hull = cv2.convexHull(np.concatenate([pts[:17], pts[17:27] - [0, 0.05 * jaw_w]]).astype(np.int32))
    cv2.fillConvexPoly(labels, hull, cv2.GC_FGD)
    border = max(2, h // 40)
    labels[:border], labels[-border:], labels[:, :border], labels[:, -border:] = (cv2.GC_BGD,) * 4
    return labels


def grabcut_mask(image: np.ndarray, landmarks: np.ndarray, iterations: int = 4) -> np.ndarray:
    labels = seed_mask(image.shape[:2], landmarks)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), labels, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    mask = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.uint8)
    # keep the component under the face, fill holes (eyes, mouth)
    count, comp = cv2.connectedComponents(mask)
    if count > 2:
        centre = landmarks[30].astype(int).clip(0, np.array(mask.shape[::-1]) - 1)
        keep = comp[centre[1], centre[0]]
        mask = (comp == keep).astype(np.uint8) if keep > 0 else mask
    filled = mask.copy()
    flood = np.zeros((mask.shape[0] + 2, mask.shape[1] + 2), np.uint8)
    cv2.floodFill(filled, flood, (0, 0), 1)
    return mask | (1 - filled)


METHODS = {"grabcut": grabcut_mask}


def temporal_vote(masks: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or len(masks) < 2:
        return masks
    half = window // 2
    padded = np.concatenate([masks[:1].repeat(half, 0), masks, masks[-1:].repeat(half, 0)])
    votes = np.stack([padded[k:k + len(masks)] for k in range(window)]).astype(np.float32).mean(0)
    return (votes >= 0.5).astype(np.uint8)


def fill_missing(masks: np.ndarray, found: np.ndarray) -> np.ndarray:
    if found.all() or not found.any():
        return masks
    idx = np.nonzero(found)[0]
    for i in np.nonzero(~found)[0]:
        masks[i] = masks[idx[np.argmin(np.abs(idx - i))]]
    return masks


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


@entry_point(READS)
def main(cfg, device) -> None:
    subject_dir = Path(cfg.preprocess.subject_dir)
    frames, meta = SubjectDir(subject_dir).frames(), SubjectDir(subject_dir).frames_meta()
    points, found = SubjectDir(subject_dir).landmarks()
    method = METHODS[cfg.preprocess.mask.method]
    masks = np.zeros(frames.shape[:3], np.uint8)
    for i in tqdm(np.nonzero(found)[0], desc="masks", unit="frame", disable=None):
        masks[i] = method(frames[i], points[i], int(cfg.preprocess.mask.iterations))
    masks = temporal_vote(fill_missing(masks, found), int(cfg.preprocess.mask.temporal_window))
    report = {"frames": len(frames), "from_landmarks": int(found.sum()), "method": cfg.preprocess.mask.method,
              "mean_coverage": float(masks.mean())}
    truth = cfg.preprocess.get("truth")
    if truth and Path(truth).is_file():
        from avatarlab.preprocess.crop import crop_and_resize, frame_crops

        with np.load(truth) as t:
            gt = np.stack([crop_and_resize(m * 255, crop, meta["size"]) > 127
                           for m, crop in zip(t["masks"][: len(masks)], frame_crops(meta))])
        ious = [iou(m > 0, g) for m, g in zip(masks, gt)]
        report.update({"iou_mean": float(np.mean(ious)), "iou_min": float(np.min(ious))})
    with atomic_path(subject_dir / "masks.npz") as tmp:
        np.savez_compressed(tmp, masks=masks)
    write_json(subject_dir / "masks.json", report)
    log.info("masks: %d frames, coverage %.3f%s", len(masks), report["mean_coverage"],
             f", IoU vs truth {report['iou_mean']:.3f}" if "iou_mean" in report else "")


if __name__ == "__main__":
    main()
