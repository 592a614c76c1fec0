"""Types and ranges of every config setting: structured-config schemas (dataclasses) for the sections of conf/.

The values live in conf/ only; a schema says what each key must be: its type (`int`, `float`, `str`, `bool`, lists,
`Optional` for a setting that may be null), a lower bound (`at_least`) and the allowed words (`one_of`). `validate`
checks a composed config against all of them - a wrong type (`pretrain.lr=abc`), a negative size, an unknown
choice - and raises one ConfigError that names every key at fault and what it should be. The workflow calls it while
planning (so `snakemake -n` fails before any job), every step calls it at start.
"""
from __future__ import annotations

import typing
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Optional

from omegaconf import DictConfig, OmegaConf

from avatarlab.runtime.errors import ConfigError


def at_least(bound: float):
    return field(default=MISSING, metadata={"min": bound})


def in_range(low: float, below: float):
    """low <= value < below."""
    return field(default=MISSING, metadata={"min": low, "below": below})


def bounded(low: float, high: float):
    """low <= value <= high: every size (pixels, samples, widths, batches), so that a typo such as
    `scale.crop_size=100000` is refused while planning instead of allocating tens of gigabytes in a step."""
    return field(default=MISSING, metadata={"min": low, "max": high})


#: upper bounds of sizes: far above the paper scale's (512 px images, 64 feature maps, 8x384 MLP, 64 samples, batch 64)
PIXELS, FEATURE_PIXELS, WIDTH, DEPTH, SAMPLES, BATCH = 4096, 512, 4096, 64, 1024, 4096


def one_of(*choices: str):
    return field(default=MISSING, metadata={"choices": choices})


@dataclass
class Paths:
    results: str
    cache: str


@dataclass
class Render:
    background: list[float]
    backface_shade: float


@dataclass
class Demo:
    out: str
    image_size: int = bounded(8, PIXELS)
    columns: int = at_least(1)
    camera_distance: float = at_least(0.01)


@dataclass
class DlibCheck:
    out: str
    overlay: str
    renders: int = at_least(1)
    image_size: int = bounded(32, PIXELS)
    coefficient_std: float = at_least(0)
    camera_distance: float = at_least(0.01)
    min_detection_rate: float = at_least(0)
    max_nme: float = at_least(0)


@dataclass
class Subject:
    name: str
    preset: str = one_of("talking", "head_turns")
    seed: int = MISSING
    fps: float = at_least(1)
    identity_std: float = at_least(0)
    camera_distance: float = at_least(0.01)
    camera_yaw: float = MISSING
    camera_pitch: float = MISSING
    fov_height: float = at_least(0.01)
    background: list[float] = MISSING
    image_noise: float = at_least(0)
    video_out: str = MISSING
    truth_out: str = MISSING
    images_out: str = MISSING
    frames: int = at_least(2)
    video_size: int = bounded(32, PIXELS)
    portraits: int = at_least(1)


@dataclass
class Preprocess:
    subject_dir: str
    inputs: list[str]
    truth: Optional[str]
    image_size: int = bounded(32, PIXELS)
    fps: Optional[float] = at_least(0.001)
    max_frames: Optional[int] = at_least(1)
    crop_margin: float = at_least(0)
    crop_samples: int = at_least(1)
    crop_per_clip: bool = MISSING
    detector_upsample: int = at_least(0)
    min_face_share: float = at_least(0)
    max_missing_frames: float = at_least(0)
    mask: dict = MISSING


@dataclass
class FitRGB:
    mode: str = one_of("video", "images")
    lr: float = at_least(0)
    initial_focal: float = at_least(0.01)
    max_keyframes: int = at_least(1)
    rigid_iterations: int = at_least(0)
    keyframe_iterations: int = at_least(0)
    frame_rigid_iterations: int = at_least(0)
    frame_iterations: int = at_least(0)
    chunk: int = at_least(1)
    lighting_per_clip: bool = MISSING
    lighting_iterations: int = at_least(0)
    lighting_lr: float = at_least(0)
    lighting_frames: int = at_least(1)
    jaw_limits_deg: list[float] = MISSING
    weights: dict = MISSING
    video_expression_reg: float = at_least(0)
    held_out: dict = MISSING   # test_frames, test_clips, validation_frames, validation_clips, recording_test_frames
    #                            (the avatar's split)


@dataclass
class FitRGBD:
    out: str
    video: str
    rgb_report: Optional[str]
    frames: int = at_least(1)
    lr: float = at_least(0)
    block_iterations: list[int] = MISSING
    texture_iterations: int = at_least(0)
    block_weights: list[float] = MISSING
    prior_weight: float = at_least(0)
    cosine_decay: bool = MISSING
    depth_noise_m: float = at_least(0)
    crop_margin_m: float = at_least(0)
    max_points: int = at_least(1)
    detected_landmarks: bool = MISSING


@dataclass
class Interp:
    width: int = bounded(1, WIDTH)
    scales: int = at_least(1)
    flow_init: str = one_of("zero", "farneback")
    keep_unwarped: bool = MISSING
    still_flow_candidates: list[float] = MISSING
    subject_still_flow_candidates: list[float] = MISSING
    loss: str = one_of("l1", "l2")
    lr: float = at_least(0)
    batch: int = bounded(1, BATCH)
    iterations: int = at_least(0)
    checkpoint_every: int = at_least(1)
    validation_every: int = at_least(0)
    strides: list[int] = MISSING
    subject_dirs: list[str] = MISSING
    motion_dirs: list[str] = MISSING
    out_dir: str = MISSING
    model: str = MISSING


@dataclass
class Tracking:
    enabled: bool
    experiment: str
    scale: str
    sweep: Optional[str] = None
    point: Optional[str] = None
    point_overrides: Optional[str] = None


@dataclass
class Model:
    renderer: str = one_of("proposed", "baseline")
    image_size: int = bounded(8, PIXELS)
    feature_size: int = bounded(1, FEATURE_PIXELS)
    frequencies: int = at_least(0)
    depth: int = bounded(1, DEPTH)
    width: int = bounded(1, WIDTH)
    skip_layer: int = at_least(0)
    feature_channels: int = at_least(1)
    samples: int = bounded(2, SAMPLES)
    density_scale: float = at_least(0.001)
    renderer_min_channels: int = at_least(1)
    mlp_precision: str = one_of("float32", "bfloat16")
    w_mse: float = at_least(0)
    w_perceptual: float = at_least(0)
    w_mask: float = at_least(0)
    vgg16_weights: Optional[str] = MISSING
    offset_weights: dict = MISSING


@dataclass
class Synthetic:
    coefficient_noise: float = at_least(0)
    neck_deg: list[float] = MISSING
    jaw_open: list[float] = MISSING
    camera_distance: list[float] = MISSING
    camera_yaw_deg: float = at_least(0)
    camera_pitch_deg: float = at_least(0)
    focal_over_size: float = at_least(0.01)


@dataclass
class Pretrain:
    name: Optional[str]
    out_dir: str
    real_subject_dir: str
    init_model: Optional[str]
    alpha_iterations: int = at_least(1)
    beta_iterations: int = at_least(0)
    iterations: Optional[int] = at_least(1)
    batch: int = bounded(1, BATCH)
    lr: float = at_least(0)
    renderer_lr: float = at_least(0)
    offset_lr: float = at_least(0)
    lr_decay: str = one_of("none", "cosine")
    lr_final: float = at_least(0)
    ema_decay: float = in_range(0, 1)
    z_aug_range: list[float] = MISSING
    checkpoint_every: int = at_least(1)
    log_every: int = at_least(1)


@dataclass
class Finetune:
    name: str
    subject: str
    subject_dir: str
    init_model: Optional[str]
    init_name: str
    out_dir: str
    iterations: int = at_least(1)
    batch: int = bounded(1, BATCH)
    lr: float = at_least(0)
    renderer_lr: float = at_least(0)
    offset_lr: float = at_least(0)
    lr_decay: str = one_of("none", "cosine")
    lr_final: float = at_least(0)
    ema_decay: float = in_range(0, 1)
    fixed_codes: list[str] = MISSING
    w_st_lpips: float = at_least(0)
    st_lpips_crop: int = at_least(0)
    st_lpips_decay: float = bounded(0, 1)
    st_lpips_net: str = one_of("alex", "vgg")
    w_distortion: float = at_least(0)
    freeze_layers: int = at_least(0)
    z_aug: bool = MISSING
    z_aug_range: list[float] = MISSING
    p_max: float = at_least(0)
    test_frames: int = at_least(1)
    test_clips: int = at_least(0)
    validation_frames: int = at_least(0)
    validation_clips: int = at_least(0)
    recording_test_frames: int = at_least(0)
    frames_variant: str = one_of("a", "b", "c")
    interpolated: str = MISSING
    checkpoint_every: int = at_least(1)
    snapshots: int = at_least(1)
    log_every: int = at_least(1)


@dataclass
class Evaluate:
    model: Optional[str]
    out: Optional[str]
    real_subject_dir: str
    samples: int = at_least(1)
    baseline_pool: int = at_least(1)
    mouth_open_frames: int = at_least(1)
    trained_frames: int = at_least(0)
    st_lpips: bool = MISSING
    lpips_backbone: Optional[str] = MISSING
    face_metrics: bool = MISSING


@dataclass
class Strategy:
    name: str
    init: Optional[str]
    M: int = at_least(0)
    N: int = at_least(0)
    p_min: float = at_least(0)
    p_max: float = at_least(0)
    z_aug: bool = MISSING
    mouth_from: Optional[int] = at_least(0)


@dataclass
class Speech:
    corpus: str
    voice: str
    out_dir: str
    wav: Optional[str]
    say: Optional[str]
    animate_model: str
    voices: list[str]
    augment: dict
    real_clips: list[str]
    real_models: list[str]
    real_eval_out: Optional[str]
    name: str
    model: str = one_of("lstm", "window")
    regularize: bool = MISSING
    phoneme_head: bool = MISSING
    sample_rate: int = at_least(1000)
    coarticulation_frames: float = at_least(0)
    landmark_noise_m: float = at_least(0)
    split_fractions: list[float] = MISSING
    lr: float = at_least(0)
    weight_decay: float = at_least(0)
    lambda1: float = at_least(0)
    lambda2: float = at_least(0)
    chunk_frames: int = at_least(1)
    batch: int = bounded(1, BATCH)
    k_x: int = at_least(1)
    k_y: int = at_least(1)
    window_inputs: str = one_of("linguistic", "one_hot")
    window_batch: int = bounded(1, BATCH * 100)
    speakers: int = at_least(3)
    utterances: int = at_least(1)
    epochs: int = at_least(1)
    channels: int = at_least(1)
    hidden: int = at_least(1)
    pca: int = at_least(1)
    window_hidden: int = at_least(1)
    adapt_epochs: int = at_least(0)
    adapt_lr: float = at_least(0)
    adapt_repeats: int = at_least(1)
    adapt_seeds: int = at_least(1)
    real_clips_per_speaker: Optional[int] = at_least(1)


@dataclass
class Apps:
    avatar: Optional[str]
    subject_dir: str
    source_dir: Optional[str]
    out: Optional[str]
    max_frames: int = at_least(1)
    yaw_deg: list[float] = MISSING
    neck_deg: list[float] = MISSING
    jaw_rad: list[float] = MISSING
    distance_offsets: list[float] = MISSING
    expression_values: list[float] = MISSING
    jpeg_quality: list[int] = MISSING


@dataclass
class Controls:
    models: list[str]
    subject_dirs: list[str]
    out: Optional[str]
    control: str = one_of("fitted", "jaw", "distance", "neck", "expression")
    jaw_rad: list[float] = MISSING
    neck_deg: list[float] = MISSING
    distance_offsets: list[float] = MISSING
    expression_values: list[float] = MISSING


@dataclass
class Report:
    results_dir: str
    out_dir: str
    final_recipe: str
    scale: str
    planned: Optional[str] = None


SECTIONS = {"paths": Paths, "render": Render, "demo": Demo, "dlib_check": DlibCheck, "subject": Subject,
            "preprocess": Preprocess, "fit_rgb": FitRGB, "fit_rgbd": FitRGBD, "interp": Interp, "tracking": Tracking,
            "model": Model, "synthetic": Synthetic, "pretrain": Pretrain, "finetune": Finetune, "evaluate": Evaluate,
            "strategy": Strategy, "speech": Speech, "apps": Apps, "controls": Controls,
            "report": Report}
TOP_LEVEL = {"seed": (int, 0), "threads": (int, 1), "amp": (bool, None), "device": (str, None)}


def _type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return f"{_type_name(args[0])} or null"
    if origin is list:
        return f"a list of {_type_name(typing.get_args(tp)[0])}" if typing.get_args(tp) else "a list"
    return {int: "an integer", float: "a number", str: "a string", bool: "true/false", dict: "a mapping",
            Any: "anything"}.get(tp, str(tp))


def _fits(value, tp) -> bool:
    origin = typing.get_origin(tp)
    if tp is Any:
        return True
    if origin is typing.Union:
        return value is None or any(_fits(value, a) for a in typing.get_args(tp) if a is not type(None))
    if origin is list:
        inner = typing.get_args(tp)
        return isinstance(value, list) and (not inner or all(_fits(v, inner[0]) for v in value))
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, tp)


def problems(cfg: DictConfig) -> list[str]:
    """Every key of `cfg` (the sections it has) that does not fit its schema, as 'key: what is wrong'."""
    found = []
    for key, (tp, low) in TOP_LEVEL.items():
        if key in cfg:
            value = cfg[key]
            if not _fits(value, tp):
                found.append(f"{key}: expected {_type_name(tp)}, got {value!r}")
            elif low is not None and value < low:
                found.append(f"{key}: must be at least {low}, got {value!r}")
    for section, schema in SECTIONS.items():
        if section not in cfg:
            continue
        try:
            values = OmegaConf.to_container(cfg[section], resolve=True)
        except Exception as err:  # an interpolation that does not resolve
            found.append(f"{section}: {str(err).splitlines()[0]}")
            continue
        raw = OmegaConf.to_container(cfg[section], resolve=False)
        hints = typing.get_type_hints(schema)
        before = len(found)
        for f in fields(schema):
            if f.name not in values:
                found.append(f"{section}.{f.name}: missing (expected {_type_name(hints[f.name])})")
                continue
            value, tp = values[f.name], hints[f.name]
            if not _fits(value, tp):
                found.append(f"{section}.{f.name}: expected {_type_name(tp)}, got {value!r}")
                continue
            low, below, choices = f.metadata.get("min"), f.metadata.get("below"), f.metadata.get("choices")
            scalar = value is not None and not isinstance(value, (list, dict))
            if scalar and low is not None and value < low:
                found.append(f"{section}.{f.name}: must be at least {low}, got {value!r}")
            if scalar and below is not None and value >= below:
                found.append(f"{section}.{f.name}: must be below {below}, got {value!r}")
            high = f.metadata.get("max")
            if scalar and high is not None and value > high:
                found.append(f"{section}.{f.name}: must be at most {high}, got {value!r}")
            if choices and value not in choices:
                found.append(f"{section}.{f.name}: expected one of {', '.join(choices)}, got {value!r}")
        for k in range(before, len(found)):  # name the setting a user typed when the key only refers to it
            key = found[k].split(":", 1)[0].split(".", 1)[-1]
            source = raw.get(key) if isinstance(raw, dict) else None
            if isinstance(source, str) and source.startswith("${") and source.endswith("}"):
                head, _, rest = found[k].partition(":")
                found[k] = f"{head} (set by {source[2:-1]}):{rest}"
        for key in values:
            if key not in hints:
                found.append(f"{section}.{key}: not a setting of {section} (the schema has "
                             f"{', '.join(sorted(hints))})")
    return found


def validate(cfg: DictConfig) -> None:
    found = problems(cfg)
    if found:
        raise ConfigError("invalid settings: " + "; ".join(found))
