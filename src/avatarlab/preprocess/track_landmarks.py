"""68 landmarks on every frame of a subject (dlib), tracked: with several faces, the one nearest the previous.

Frames without a face are flagged (found = False) and skipped by later steps, never a crash. Where the subject has a
ground truth (synthetic subjects), the report gives the NME. Writes `landmarks.npz` and `landmarks.json`.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.preprocess.crop import crop_points
from avatarlab.preprocess.landmarks import _dlib_models, normalised_mean_error
from avatarlab.runtime.entry import InputError, entry_point
from avatarlab.runtime.io import atomic_path, write_json

log = logging.getLogger(__name__)
READS = ('seed', 'preprocess')  # the config sections this step reads (runtime/entry.py)


def track(frames: np.ndarray, upsample: int):
    detector, predictor = _dlib_models()
    n = len(frames)
    points = np.full((n, 68, 2), np.nan, np.float32)
    boxes = np.full((n, 4), -1, np.int32)
    found = np.zeros(n, bool)
    previous = None
    for i, frame in enumerate(tqdm(frames, desc="landmarks", unit="frame", disable=None)):
        image = np.ascontiguousarray(frame)
        dets = list(detector(image, upsample))
        if not dets:
            continue
        if previous is not None and len(dets) > 1:
            centre = lambda b: np.array([(b.left() + b.right()) / 2, (b.top() + b.bottom()) / 2])  # noqa: E731
            det = min(dets, key=lambda b: np.linalg.norm(centre(b) - previous))
        else:
            det = max(dets, key=lambda b: b.width() * b.height())
        shape = predictor(image, det)
        points[i] = [[p.x, p.y] for p in shape.parts()]
        boxes[i] = [det.left(), det.top(), det.right(), det.bottom()]
        found[i] = True
        previous = np.array([(det.left() + det.right()) / 2, (det.top() + det.bottom()) / 2])
    return points, boxes, found


def truth_landmarks(truth_path: Path | None, meta: dict) -> np.ndarray | None:
    if truth_path is None or not Path(truth_path).is_file():
        return None
    with np.load(truth_path) as truth:
        return crop_points(truth["landmarks2d"][: meta["count"]], meta)


@entry_point(READS)
def main(cfg, device) -> None:
    subject_dir = Path(cfg.preprocess.subject_dir)
    frames, meta = SubjectDir(subject_dir).frames(), SubjectDir(subject_dir).frames_meta()
    points, boxes, found = track(frames, int(cfg.preprocess.detector_upsample))
    report = {"frames": len(frames), "found": int(found.sum()), "detection_rate": float(found.mean()),
              "missing_frames": np.nonzero(~found)[0].tolist()}
    share = float(cfg.preprocess.min_face_share)
    if found.mean() < share:  # judged here, where it enters: no later step can make up for a missing face
        inputs = ", ".join(meta.get("inputs", [])) or str(subject_dir / "frames")
        raise InputError(f"subject {subject_dir.name}: dlib finds a face in {int(found.sum())} of {len(frames)} "
                         f"frames ({found.mean():.0%}) of {inputs}; at least {share:.0%} are needed "
                         "(preprocess.min_face_share)")
    gt = truth_landmarks(cfg.preprocess.get("truth"), meta)
    if gt is not None and found.any():
        nmes = [normalised_mean_error(points[i], gt[i]) for i in np.nonzero(found)[0]]
        report.update({"nme_mean": float(np.mean(nmes)), "nme_median": float(np.median(nmes))})
    with atomic_path(subject_dir / "landmarks.npz") as tmp:
        np.savez(tmp, points=points, boxes=boxes, found=found)
    write_json(subject_dir / "landmarks.json", report)
    log.info("landmarks: face found in %d/%d frames%s", found.sum(), len(frames),
             f", NME {report['nme_mean']:.4f} vs ground truth" if "nme_mean" in report else "")


if __name__ == "__main__":
    main()
