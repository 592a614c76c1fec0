"""The frame interpolator trained once, on every video the platform has, then used for every subject.

XVFI (Sim et al. 2021; seed 002, section 4.3) is a network trained on a large video set and then applied to new
footage, not one trained per subject. Here it learns from all subjects' videos at once (the synthetic subjects and
the real clips, each at the motion speeds `interp.strides` names; the default, stride 1 only, is the closest to the
held-out frames' own motion): triplets (left, middle, right) of frames `stride` apart among the frames variant (b)
keeps, for every stride in `interp.strides`, so the frames any subject's experiment holds out are never seen.
Writes `model.pt` (weights only) and `train.json` into `interp.out_dir`; a killed run resumes.
`python -m avatarlab.preprocess.interp.pretrain 'interp.subject_dirs=[results/tiny/subjects/synth_talk,...]'`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.preprocess.interp.network import save_interpolator
from avatarlab.preprocess.interp.training import (
    choose_still_flow,
    split_variants,
    to_tensor,
    train,
    training_triplets,
    validation_split,
)
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json

log = logging.getLogger(__name__)
READS = ('seed', 'amp', 'interp')  # the config sections this step reads (runtime/entry.py)


def split_by_stride_one(kept: np.ndarray, strides, clips, validation_every: int) -> tuple[np.ndarray, np.ndarray]:
    """(training, validation) triplets of one video. The validation triplets are always stride-1 ones (the gap the
    held-out frames sit in), whatever `strides` trains on, so runs with different strides are scored on the same
    triplets; no training triplet of any stride has a validation triplet's middle frame as its target."""
    _, held = validation_split(training_triplets(kept, (1,), clips), validation_every)
    found = training_triplets(kept, strides, clips)
    return found[~np.isin(found[:, 1], held[:, 1])], held


def gather(subject_dirs, strides, validation_every: int = 0,
           motion_dirs=()) -> tuple[torch.Tensor, np.ndarray, dict, np.ndarray]:
    """Every video's frames in one tensor (all crops have the scale's size), the training triplets into it and the
    validation triplets (every `validation_every`-th of each video's, 0: none; (M, 4): the triplet and the index
    of its video) that choose the snapshot. A subject's triplets use only the frames its variant (b) keeps
    (neighbours 4 frames apart at stride 1); a motion video's (`motion_dirs`: no experiment holds frames out of it)
    use every frame, so at stride 1 its neighbours are 2 frames apart, the gap the held-out frames sit in."""
    frames, triplets, validation, counts, offset = [], [], [], {}, 0
    videos = [(folder, False) for folder in subject_dirs] + [(folder, True) for folder in motion_dirs]
    for index, (folder, whole) in enumerate(videos):
        subject = SubjectDir(folder)
        images, clips = to_tensor(subject.frames()), subject.frame_clips()
        kept = np.arange(len(images)) if whole else split_variants(len(images), clips)[0]
        found, held = split_by_stride_one(kept, strides, clips, validation_every)
        frames.append(images)
        triplets.append(found + offset)
        validation.append(np.concatenate([held + offset, np.full((len(held), 1), index)], 1))
        counts[Path(folder).name] = {"frames": len(images), "triplets": len(found), "validation": len(held)}
        offset += len(images)
    sizes = {tuple(f.shape[1:]) for f in frames}
    if len(sizes) > 1:
        raise ValueError(f"interp.subject_dirs: the subjects' frames differ in size {sorted(sizes)}")
    return torch.cat(frames), np.concatenate(triplets), counts, np.concatenate(validation)


def train_interpolator(cfg, device) -> dict:
    """The step: trains on every subject in `interp.subject_dirs`, writes model.pt and train.json -> the report."""
    ip = cfg.interp
    out_dir = Path(ip.out_dir)
    if not ip.subject_dirs:
        raise ValueError("interp.subject_dirs: no subject to learn interpolation from")
    frames, triplets, counts, validation = gather(list(ip.subject_dirs), list(ip.strides), int(ip.validation_every),
                                                  list(ip.motion_dirs))
    if len(triplets) == 0:
        raise ValueError(f"interp.subject_dirs: too few frames for a triplet at strides {list(ip.strides)}")
    start = time.perf_counter()
    data = {f"frames_{k}": Path(d) / "frames.json" for k, d in enumerate([*ip.subject_dirs, *ip.motion_dirs])}
    model, losses, chosen = train(frames, triplets, cfg, out_dir / "checkpoint.pt", device, data=data,
                                  validation=validation[:, :3], validation_groups=validation[:, 3])
    still = choose_still_flow(model, frames, validation[:, :3], device, validation[:, 3],
                              list(ip.still_flow_candidates))
    report = {"subjects": counts, "strides": list(ip.strides), "triplets": len(triplets),
              "validation_triplets": len(validation), "iterations": len(losses),
              "train_seconds": time.perf_counter() - start, "loss": str(ip.loss),
              "first_train_loss": float(np.mean(losses[:20])), "final_train_loss": float(np.mean(losses[-20:])),
              "validation_psnr_curve": chosen["curve"],
              "chosen_step": chosen["best_step"], "chosen_validation_psnr": chosen["best_psnr"],
              "still_flow_px": model.still_flow_px, "still_flow_validation_psnr": still}
    save_interpolator(out_dir / "model.pt", model, len(losses))
    write_json(out_dir / "train.json", report)
    (out_dir / "checkpoint.pt").unlink(missing_ok=True)  # finished: nothing a later run could mistake for its own
    return report


@entry_point(READS)
def main(cfg, device) -> None:
    report = train_interpolator(cfg, device)
    log.info("frame interpolator: %d triplets of %d subjects (strides %s), %d iterations in %.0f s, train %s "
             "loss %.5f -> %.5f", report["triplets"], len(report["subjects"]), report["strides"], report["iterations"],
             report["train_seconds"], report["loss"].upper(), report["first_train_loss"], report["final_train_loss"])
    if report["chosen_step"] is not None:
        curve = dict((int(k), v) for k, v in report["validation_psnr_curve"])
        log.info("kept the snapshot of step %d: %.2f dB on %d validation triplets (step 0, the untrained blend of "
                 "its starting flows: %.2f dB; the last step: %.2f dB)", report["chosen_step"],
                 report["chosen_validation_psnr"], report["validation_triplets"], curve[0], curve[max(curve)])
    if report["still_flow_validation_psnr"]:
        log.info("pixels whose flow is shorter than %.2f px are not warped (validation PSNR by that length: %s)",
                 report["still_flow_px"], ", ".join(f"{c:g} px {v:.2f} dB" for c, v in report["still_flow_validation_psnr"]))


if __name__ == "__main__":
    main()
