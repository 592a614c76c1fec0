"""Which frames of a subject an avatar trains on and which it is tested on.

- INSTA protocol (seed 002, 4.1): the last `test_frames` frames are the test split, the ones before it train.
- Held-out clips (`test_clips` > 0, a subject made of several clips): every frame of the last `test_clips` clips is a
  test frame, so the avatar is also scored on a recording it never saw (another session, the head elsewhere in the
  crop).
- Validation (`validation_frames` / `validation_clips`, not in the dissertation, which fine-tunes a fixed number of
  iterations): the frames just before the test frames, or the clip(s) just before the test clip(s), are held out of
  training too. Fine-tuning scores its snapshots on them and keeps the best (avatar/finetune.py), so the stop is chosen
  on frames that extrapolate as the test frames do, and the test frames stay unseen.
- Same-recording test frames (`recording_test_frames` > 0, held-out clips only; not in the dissertation): the last
  frames of every training clip are held out too and scored apart (evaluation's `same_recording`): frames of a
  recording the avatar trained on, later in it, as in the INSTA protocol, beside the held-out clips' new recordings.
  Each training clip keeps at least its first frame.
- Interpolation experiment (section 4.3): variant b keeps every second training frame (the even ones), c adds back
  the dropped ones re-created by the frame interpolator.
Too few frames for the asked split stops with a line naming the subject's frames file.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.runtime.entry import InputError


@dataclass
class Split:
    train: np.ndarray  # frame indices the avatar trains on
    test: np.ndarray  # frame indices it is scored on
    protocol: str  # "last_frames" or "held_out_clips"
    validation: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # frames held out to choose the stop
    recording: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # the last frames of the training
    #                                                                           clips, scored apart (same recording)

    @property
    def seen(self) -> np.ndarray:
        """Every frame the avatar's run saw (training and validation): what the trivial baselines may copy."""
        return np.union1d(self.train, self.validation)


def held_out(clips: np.ndarray, test_frames: int, test_clips: int = 0, validation_frames: int = 0,
             validation_clips: int = 0, source: str = "the subject",
             recording_test_frames: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
    """Which frames an avatar is tested and validated on, from the frame count and clips alone (so preprocessing
    can keep them out of the identity fit before anything is fitted). clips (N,) clip index of each frame ->
    (in_test (N,) bool, in_validation (N,) bool, protocol); in_test includes the same-recording test frames
    (`recording_tails`)."""
    in_test, in_recording, in_validation, protocol = _held_out(clips, test_frames, test_clips, validation_frames,
                                                               validation_clips, source, recording_test_frames)
    return in_test | in_recording, in_validation, protocol


def recording_tails(clips: np.ndarray, excluded: np.ndarray, count: int) -> np.ndarray:
    """(N,) bool: the last `count` frames of every clip none of whose frames is `excluded` (the training clips of the
    held-out-clips protocol), each clip keeping at least its first frame."""
    clips = np.asarray(clips)
    tails = np.zeros(len(clips), bool)
    if count <= 0:
        return tails
    for clip in dict.fromkeys(clips.tolist()):
        members = np.nonzero(clips == clip)[0]
        if excluded[members].any():
            continue
        tails[members[max(1, len(members) - count):]] = True
    return tails


def _held_out(clips, test_frames, test_clips, validation_frames, validation_clips, source, recording_test_frames):
    """held_out's parts: (in_test, in_recording, in_validation, protocol); same-recording frames only with held-out
    clips (the last-frames protocol's test frames already are its recording's last)."""
    n = len(clips)
    idx = np.arange(n)
    if test_clips > 0:
        order = list(dict.fromkeys(np.asarray(clips).tolist()))
        if len(order) <= test_clips + validation_clips:
            raise InputError(f"{source}: {len(order)} clip(s) cannot hold out {test_clips} clip(s) for testing"
                             + (f" and {validation_clips} for validation" if validation_clips else "")
                             + " and still train on another (finetune.test_clips, finetune.validation_clips)")
        in_test = np.isin(clips, order[-test_clips:])
        in_validation = np.isin(clips, order[len(order) - test_clips - validation_clips:len(order) - test_clips])
        return (in_test, recording_tails(clips, in_test | in_validation, recording_test_frames), in_validation,
                "held_out_clips")
    if n < 2 * test_frames + validation_frames:
        raise InputError(f"{source}: {n} frames are too few for {test_frames} test frames"
                         + (f", {validation_frames} validation frames" if validation_frames else "")
                         + " and at least as many training frames as test frames (finetune.test_frames="
                         f"{test_frames}, finetune.validation_frames={validation_frames})")
    in_test = idx >= n - test_frames
    in_validation = (idx >= n - test_frames - validation_frames) & ~in_test
    return in_test, np.zeros(n, bool), in_validation, "last_frames"


def subject_split(fitted: np.ndarray, clips: np.ndarray, test_frames: int, test_clips: int = 0, variant: str = "a",
                  interpolated=(), source: str = "the subject", validation_frames: int = 0,
                  validation_clips: int = 0, recording_test_frames: int = 0) -> Split:
    """fitted (N,) bool, clips (N,) clip index of each frame. validation_frames applies to the last-frames
    protocol, validation_clips and recording_test_frames to the held-out-clips one."""
    if variant not in ("a", "b", "c"):
        raise InputError(f"finetune.frames_variant={variant!r}: expected a, b or c")
    n = len(fitted)
    idx = np.arange(n)
    in_test, in_recording, in_validation, protocol = _held_out(clips, test_frames, test_clips, validation_frames,
                                                               validation_clips, source, recording_test_frames)
    test = idx[in_test & fitted]
    validation = idx[in_validation & fitted]
    recording = idx[in_recording & fitted]
    in_test = in_test | in_recording
    in_train = ~in_test & ~in_validation & fitted
    if variant in ("b", "c"):
        kept = in_train & (idx % 2 == 0)
        if variant == "c":
            made = np.zeros(n, bool)
            made[np.asarray(list(interpolated), dtype=int)] = True
            kept |= ~in_test & ~in_validation & made
        in_train = kept
    train = idx[in_train]
    if len(test) == 0 or len(train) == 0:
        raise InputError(f"{source}: no fitted frame left for the {'test' if len(test) == 0 else 'training'} split "
                         f"({int(fitted.sum())} of {n} frames fitted)")
    if (validation_clips if test_clips > 0 else validation_frames) > 0 and len(validation) == 0:
        raise InputError(f"{source}: no fitted frame in the validation split ({int(fitted.sum())} of {n} frames "
                         "fitted)")
    return Split(train=train, test=test, protocol=protocol, validation=validation, recording=recording)


def mouth_open_subset(jaw: np.ndarray, count: int) -> np.ndarray:
    """Positions (into the test frames) of the `count` frames with the widest fitted jaw opening."""
    return np.argsort(-np.asarray(jaw))[: max(1, min(count, len(jaw)))]


def avatar_split(ft) -> Split:
    """The split of an avatar described by a `finetune` config section (fine-tuning and evaluation use this)."""
    subject = SubjectDir(ft.subject_dir)
    fitted = subject.fit(per_frame=False)["fitted"].astype(bool)
    made = subject.interpolated(ft.interpolated)[0] if ft.frames_variant == "c" else ()
    return subject_split(fitted, subject.frame_clips(), int(ft.test_frames), int(ft.test_clips),
                         str(ft.frames_variant), made, source=str(subject.frames_json),
                         validation_frames=int(ft.validation_frames),
                         validation_clips=int(ft.validation_clips),
                         recording_test_frames=int(ft.recording_test_frames))
