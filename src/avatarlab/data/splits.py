"""Which frames of a subject an avatar trains on and which it is tested on.

- INSTA protocol (seed 002, 4.1): the last `test_frames` frames are the test split, the ones before it train.
- Held-out clips (`test_clips` > 0, a subject made of several clips): every frame of the last `test_clips` clips is a
  test frame, so the avatar is also scored on a recording it never saw (another session, the head elsewhere in the
  crop).
- Interpolation experiment (section 4.3): variant b keeps every second training frame (the even ones), c adds back
  the dropped ones re-created by the frame interpolator.
Too few frames for the asked split stops with a line naming the subject's frames file.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.entry import InputError


@dataclass
class Split:
    train: np.ndarray  # frame indices the avatar trains on
    test: np.ndarray  # frame indices it is scored on
    protocol: str  # "last_frames" or "held_out_clips"


def subject_split(fitted: np.ndarray, clips: np.ndarray, test_frames: int, test_clips: int = 0, variant: str = "a",
                  interpolated=(), source: str = "the subject") -> Split:
    """fitted (N,) bool, clips (N,) clip index of each frame."""
    if variant not in ("a", "b", "c"):
        raise InputError(f"finetune.frames_variant={variant!r}: expected a, b or c")
    n = len(fitted)
    idx = np.arange(n)
    if test_clips > 0:
        order = list(dict.fromkeys(clips.tolist()))
        if len(order) <= test_clips:
            raise InputError(f"{source}: {len(order)} clip(s) cannot hold out {test_clips} clip(s) for testing "
                             "and still train on another (finetune.test_clips)")
        in_test = np.isin(clips, order[-test_clips:])
        protocol = "held_out_clips"
    else:
        if n < 2 * test_frames:
            raise InputError(f"{source}: {n} frames are too few for {test_frames} test frames and at least as many "
                             f"training frames (finetune.test_frames={test_frames})")
        in_test = idx >= n - test_frames
        protocol = "last_frames"
    test = idx[in_test & fitted]
    in_train = ~in_test & fitted
    if variant in ("b", "c"):
        kept = in_train & (idx % 2 == 0)
        if variant == "c":
            made = np.zeros(n, bool)
            made[np.asarray(list(interpolated), dtype=int)] = True
            kept |= ~in_test & made
        in_train = kept
    train = idx[in_train]
    if len(test) == 0 or len(train) == 0:
        raise InputError(f"{source}: no fitted frame left for the {'test' if len(test) == 0 else 'training'} split "
                         f"({int(fitted.sum())} of {n} frames fitted)")
    return Split(train=train, test=test, protocol=protocol)


def mouth_open_subset(jaw: np.ndarray, count: int) -> np.ndarray:
    """Positions (into the test frames) of the `count` frames with the widest fitted jaw opening."""
    return np.argsort(-np.asarray(jaw))[: max(1, min(count, len(jaw)))]


def avatar_split(ft) -> Split:
    """The split of an avatar described by a `finetune` config section (fine-tuning and evaluation use this)."""
    subject = SubjectDir(ft.subject_dir)
    fitted = subject.fit(per_frame=False)["fitted"].astype(bool)
    made = subject.interpolated(ft.interpolated)[0] if ft.frames_variant == "c" else ()
    return subject_split(fitted, subject.frame_clips(), int(ft.test_frames), int(ft.test_clips),
                         str(ft.frames_variant), made, source=str(subject.frames_json))
