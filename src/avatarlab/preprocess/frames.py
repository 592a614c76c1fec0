"""Frames of a subject: a video file (mp4/avi/mpg), several clips, a folder of images, or an INSTA subject folder.

Frames are read with OpenCV, subsampled to a target fps, cropped with one square head crop per recording (each
video clip, each image folder: from dlib face boxes on sampled frames of it, so the crop is stable over the clip while
every clip's head comes out centred and at the same size; `preprocess.crop_per_clip=false`: one crop for all inputs)
and resized. Writes `frames/NNNNNN.png` and `frames.json` (source of each frame, the crops, fps) atomically.
`python -m avatarlab.preprocess.frames 'preprocess.inputs=[clip1.mp4,clip2.mp4]' preprocess.subject_dir=...`
"""
from __future__ import annotations

import glob
import logging
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
from omegaconf import OmegaConf
from tqdm import tqdm

from avatarlab.preprocess.crop import crop_and_resize, frame_crops
from avatarlab.runtime.entry import InputError, entry_point
from avatarlab.runtime.io import write_json

log = logging.getLogger(__name__)
READS = ('seed', 'preprocess')  # the config sections this step reads (runtime/entry.py)
VIDEO_SUFFIXES = {".mp4", ".avi", ".mpg", ".mpeg", ".mov", ".mkv", ".webm"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp"}
MIN_SIDE = 16  # pixels: below this an input frame is refused (no face to find; the crop would be all padding)


def expand_inputs(inputs) -> list[Path]:
    paths: list[Path] = []
    for item in inputs:
        matches = sorted(glob.glob(str(item))) or [str(item)]
        paths += [Path(m) for m in matches]
    for p in paths:
        if not p.exists():
            raise InputError(f"{p}: input not found")
    return paths


def input_kind(path: Path) -> str:
    if path.is_dir():
        if list(path.glob("transforms*.json")) and (path / "images").is_dir():
            return "insta"
        return "images"
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return "video"
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return "image"
    raise InputError(f"{path}: not a video ({', '.join(sorted(VIDEO_SUFFIXES))}), image or image folder")


def check_video_stream(path: Path) -> None:
    """Decodes the video stream once with ffmpeg (imageio-ffmpeg's binary), which reports a damaged or cut-off
    stream even in formats whose container declares no frame count (MPEG-PS .mpg, where OpenCV estimates the count
    from the file's size, so a file cut in half declares half the frames). Any error stops with the file named."""
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        log.warning("%s: no ffmpeg to check the stream with; only the header's frame count is checked", path)
        return
    out = subprocess.run([exe, "-nostdin", "-v", "error", "-i", str(path), "-map", "0:v:0", "-f", "null", "-"],
                         capture_output=True, text=True, errors="replace", timeout=600)
    errors = [line.strip() for line in out.stderr.splitlines() if line.strip()]
    if out.returncode or errors:
        first = errors[0] if errors else f"exit status {out.returncode}"
        raise InputError(f"{path}: the video stream is damaged or cut off (ffmpeg: {first!r}, {len(errors)} error "
                         "line(s)); use a complete copy of the file")


def sampling_step(fps: float, target_fps: float | None) -> int:
    """Every how many frames one is taken to come near `target_fps` (None: every frame)."""
    return max(1, int(round(fps / target_fps))) if target_fps else 1


def spread(count: int, keep: int | None) -> np.ndarray:
    """Positions of `keep` of `count` frames spread evenly over them, the first and the last included (all of them
    when `keep` is None or not below `count`): a capped clip is thinned over its whole length, not cut short."""
    if keep is None or keep >= count:
        return np.arange(count)
    if keep <= 0:
        return np.arange(0)
    return np.unique(np.linspace(0, count - 1, keep).round().astype(int))


def sampled_frames(path: Path, target_fps: float | None) -> int:
    """How many frames `read_video` takes from a video at `target_fps` before any cap: from the header's frame
    count, or, where the header declares none, by counting the frames once without decoding them to images."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"{path}: OpenCV cannot open this video (corrupt file or unsupported codec)")
    step = sampling_step(cap.get(cv2.CAP_PROP_FPS) or 25.0, target_fps)
    declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    if declared <= 0:
        while cap.grab():
            declared += 1
    cap.release()
    return -(-declared // step)


def read_video(path: Path, target_fps: float | None, keep: int | None, max_missing: float = 0.1,
               count: int | None = None):
    """The frames of a video (every `fps / target_fps`-th), at most `keep` of them, spread evenly over the whole
    video (`spread`; `count`: `sampled_frames` of it when the caller has it already). A file that decodes fewer
    frames than its header declares, by more than the share `max_missing` (a truncated download, a broken encode),
    stops with the file and the counts named, rather than becoming a shorter subject unnoticed."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"{path}: OpenCV cannot open this video (corrupt file or unsupported codec)")
    check_video_stream(path)
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    step = sampling_step(fps, target_fps)
    wanted = None
    if keep is not None:
        wanted = set(spread(sampled_frames(path, target_fps) if count is None else count, keep).tolist())
    frames, index = [], 0
    while cap.grab():
        position, sampled = divmod(index, step)
        if sampled == 0 and (wanted is None or position in wanted):
            ok, frame = cap.retrieve()
            if not ok:
                break
            if not frames:
                check_size(path, frame, "video")
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        index += 1
    cap.release()
    if not frames:
        raise InputError(f"{path}: no frames could be decoded")
    if declared > 0 and index < declared * (1 - max_missing):
        raise InputError(f"{path}: only {index} of the {declared} frames its header declares could be decoded "
                         f"(truncated or damaged file; preprocess.max_missing_frames={max_missing})")
    return frames, fps / step


def check_size(path: Path, frame: np.ndarray, what: str) -> None:
    """A frame smaller than MIN_SIDE pixels a side holds no face to find: it would become a black frame."""
    h, w = frame.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise InputError(f"{path}: the {what} is {w}x{h} pixels; at least {MIN_SIDE}x{MIN_SIDE} are needed")


def read_images(paths: list[Path]):
    frames = []
    for p in paths:
        image = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if image is None:
            raise InputError(f"{p}: not a readable image")
        check_size(p, image, "image")
        frames.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    return frames


def source_label(path: Path, taken: list[str]) -> str:
    """The label of an input's frames: its file name, or its whole path when an earlier input has that name
    (two folders' `clip.mp4`), so that every input is a clip of its own (its crop, its lighting, its split)."""
    if path.name not in taken:
        return path.name
    label, k = str(path), 2
    while label in taken:  # the same file given twice
        label, k = f"{path} #{k}", k + 1
    return label


def share_frames(counts: list[int], cap: int | None) -> list[int]:
    """How many frames each input keeps: all of them when they fit in `cap`, else `cap` in all, shared as evenly as
    the inputs allow (an input with fewer frames than its share gives the rest to the others), so that a capped
    multi-clip subject still has every clip (its crop, its lighting, a clip to hold out)."""
    if not cap or sum(counts) <= cap:
        return list(counts)
    keep, left = [0] * len(counts), cap
    while left > 0:
        room = [i for i, c in enumerate(counts) if keep[i] < c]
        each = max(1, left // len(room))
        for i in room:
            take = min(each, counts[i] - keep[i], left)
            keep[i] += take
            left -= take
    return keep


def load_frames(inputs: list[Path], target_fps, max_frames, max_missing: float = 0.1):
    """-> frames (list of RGB uint8), source label per frame, fps, kind. At most `max_frames` in all, shared over
    the inputs (`share_frames`), each input's share spread over its whole length (`spread`)."""
    kinds, counts, files_of = [], [], []
    for path in inputs:
        kind = input_kind(path)
        files = None
        if kind == "video":
            count = sampled_frames(path, target_fps)
        else:
            folder = path / "images" if kind == "insta" else path
            files = [path] if kind == "image" else sorted(f for f in folder.iterdir()
                                                           if f.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise InputError(f"{folder}: no images found")
            count = len(files)
        kinds.append(kind)
        counts.append(count)
        files_of.append(files)
    shares = share_frames(counts, max_frames)
    capped = bool(max_frames) and sum(counts) > max_frames
    frames, sources, labels, fps = [], [], [], None
    for path, kind, files, count, keep in zip(inputs, kinds, files_of, counts, shares):
        if keep == 0:
            log.warning("%s: none of its frames fit in preprocess.max_frames=%s beside the other inputs", path,
                        max_frames)
            continue
        if kind == "video":
            clip, clip_fps = read_video(path, target_fps, keep if keep < count else None, max_missing, count)
            if capped:  # a header that declares fewer frames than the file holds does not lift the cap
                clip = clip[:keep]
            fps = fps or clip_fps
        else:
            clip = read_images([files[i] for i in spread(count, keep)])
            fps = fps or 25.0
        if keep < count:
            log.info("%s: %d of its %d frames, spread over it (preprocess.max_frames=%s)", path, len(clip), count,
                     max_frames)
        label = source_label(path, labels)
        labels.append(label)
        frames += clip
        sources += [label] * len(clip)
    return frames, sources, float(fps or 25.0), sorted(set(kinds))


def stable_head_crop(frames, margin: float, samples: int, upsample: int, label: str = "all") -> tuple[int, int, int]:
    """One square crop (cx, cy, side) for all frames (of the input `label`) from face boxes on up to `samples`
    of them."""
    from avatarlab.preprocess.landmarks import detect_faces

    idx = np.unique(np.linspace(0, len(frames) - 1, min(samples, len(frames))).round().astype(int))
    boxes = [b for i in idx for b in detect_faces(frames[i], upsample)[:1]]
    h, w = frames[0].shape[:2]
    if not boxes:
        log.warning("%s: no face found on %d sampled frames: using a centred crop", label, len(idx))
        side = min(h, w)
        return w // 2, h // 2, side
    boxes = np.array(boxes, dtype=np.float64)  # left, top, right, bottom
    cx = np.median((boxes[:, 0] + boxes[:, 2]) / 2)
    # dlib boxes cover brows to chin: move the centre up so hair and forehead fit
    size = np.max(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]))
    cy = np.median((boxes[:, 1] + boxes[:, 3]) / 2) - 0.15 * size
    side = int(round(size * margin))
    return int(round(cx)), int(round(cy)), side


def clip_ranges(sources: list[str]) -> list[tuple[int, int]]:
    """(first, stop) of each run of frames from one source (a clip, an image folder, an image)."""
    starts = [i for i in range(len(sources)) if i == 0 or sources[i] != sources[i - 1]]
    return list(zip(starts, starts[1:] + [len(sources)]))


def choose_crops(frames, sources, pre, kinds) -> list[dict]:
    """The crops of the frames: [{source, first, count, cx, cy, side}], one per clip or one for all."""
    if "insta" in kinds or pre.crop_margin <= 0:
        h, w = frames[0].shape[:2]
        return [{"source": "all", "first": 0, "count": len(frames), "cx": w // 2, "cy": h // 2, "side": min(h, w)}]
    ranges = clip_ranges(sources) if pre.crop_per_clip else [(0, len(frames))]
    crops = []
    for first, stop in ranges:
        source = sources[first] if len(ranges) > 1 else "all"
        cx, cy, side = stable_head_crop(frames[first:stop], float(pre.crop_margin), int(pre.crop_samples),
                                        int(pre.detector_upsample), label=source)
        crops.append({"source": source, "first": first, "count": stop - first, "cx": cx, "cy": cy, "side": side})
    return crops


def write_frames(subject_dir: Path, frames, sources, fps, crops, size, kinds, inputs) -> dict:
    out_dir = subject_dir / "frames"
    tmp_dir = subject_dir / ".frames.tmp"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp_dir.mkdir(parents=True)
    names = []
    per_frame = frame_crops({"crops": crops, "count": len(frames)})
    for i, frame in enumerate(tqdm(frames, desc="frames", unit="frame", disable=None)):
        name = f"{i:06d}.png"
        cv2.imwrite(str(tmp_dir / name), cv2.cvtColor(crop_and_resize(frame, per_frame[i], size), cv2.COLOR_RGB2BGR))
        names.append(name)
    shutil.rmtree(out_dir, ignore_errors=True)
    os.replace(tmp_dir, out_dir)
    h, w = frames[0].shape[:2]
    meta = {"count": len(names), "files": names, "sources": sources, "fps": fps, "size": size,
            "crops": crops, "original_size": [h, w], "kinds": kinds, "inputs": [str(p) for p in inputs]}
    if len(crops) == 1:  # one crop for every frame
        meta["crop"] = {k: crops[0][k] for k in ("cx", "cy", "side")}
    write_json(subject_dir / "frames.json", meta)
    return meta



@entry_point(READS)
def main(cfg, device) -> None:
    pre = cfg.preprocess
    inputs = expand_inputs(OmegaConf.to_container(pre.inputs))
    frames, sources, fps, kinds = load_frames(inputs, pre.fps, pre.max_frames, float(pre.max_missing_frames))
    crops = choose_crops(frames, sources, pre, kinds)
    meta = write_frames(Path(pre.subject_dir), frames, sources, fps, crops, int(pre.image_size), kinds, inputs)
    shown = "; ".join(f"{c['source']}: ({c['cx']}, {c['cy']}, {c['side']})" for c in crops)
    log.info("%d frames (%s) at %.2f fps, %d crop(s) %s -> %dx%d in %s/frames", meta["count"], ",".join(kinds), fps,
             len(crops), shown, pre.image_size, pre.image_size, pre.subject_dir)


if __name__ == "__main__":
    main()
