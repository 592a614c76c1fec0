"""What the dissertation and the speech papers publish (tables 2 and seed 000's), and where this platform differs
from them (the substitutions), as the report prints them."""
from __future__ import annotations

from avatarlab.report.table import Table

# Table 2 of the dissertation (seed 002, section 4.5): INSTA data, 256x256, creation time on an RTX 4090.
PUBLISHED_TABLE2 = [
    {"method": "NHA", "psnr": 25.1049, "ssim": 0.8080, "lpips": 0.0789, "creation_time": "~8 h"},
    {"method": "IMAvatar", "psnr": 25.8890, "ssim": 0.9123, "lpips": 0.0771, "creation_time": "3-7 days"},
    {"method": "PointAvatar", "psnr": 26.2529, "ssim": 0.8862, "lpips": 0.0631, "creation_time": "~1 h"},
    {"method": "INSTA", "psnr": 25.4665, "ssim": 0.9098, "lpips": 0.1066, "creation_time": "~10 min"},
    {"method": "proposed (dissertation)", "psnr": 26.2867, "ssim": 0.8952, "lpips": 0.0461,
     "creation_time": "~10 min"},
]


PUBLISHED_SECONDS = {"NHA": 8 * 3600, "IMAvatar": 5 * 86400, "PointAvatar": 3600, "INSTA": 600,
                     "proposed (dissertation)": 600}


# Seed 000's table (GRID): latency and lip-landmark error normalised by the outer-eye distance.
PUBLISHED_SPEECH = [
    {"method": "NVIDIA (Karras et al. 2017)", "latency_ms": 260, "lip_error_iod": None},
    {"method": "VisemeNet", "latency_ms": 950, "lip_error_iod": 2.5},
    {"method": "seed 000, with regularisation", "latency_ms": 130, "lip_error_iod": 1.9},
    {"method": "seed 000, without regularisation", "latency_ms": 130, "lip_error_iod": 2.1},
]


#: where this platform uses something other than the dissertation (seed 002) or the speech papers, and why
SUBSTITUTIONS = [
    ("head model", "FLAME 2020", "a procedural FLAME-structured head (same joints, blend shapes, 68-point "
     "embedding, PCA albedo, SH lighting)", "FLAME's licence; the real model is used when given by path"),
    ("real image set", "FFHQ (70 000 photographs)", "procedurally varied portraits of the head model (hair caps, "
     "backgrounds, lighting, noise), preprocessed and fitted like photographs", "licence, no downloads; real photos "
     "by path"),
    ("avatar videos", "INSTA's videos", "two synthetic subject videos with ground truth, and the obama clips where "
     "present", "licence, no downloads"),
    ("landmarks", "FAN", "dlib's 68-point detector (face_recognition_models)", "no downloaded weights"),
    ("head masks", "BiSeNet face parsing", "GrabCut seeded from the landmarks, smoothed over time",
     "no downloaded weights"),
    ("perceptual loss", "VGG16 (ImageNet)", "fixed random-conv features unless VGG16 weights are given",
     "ImageNet weights are a licensed optional input"),
    ("LPIPS", "LPIPS-VGG", "LPIPS-VGG only with its backbone given (else 'missing'); ST-LPIPS (AlexNet, weights in "
     "its wheel) reported under its own name", "never a substitute under LPIPS's name"),
    ("frame interpolation", "XVFI trained on X4K1000FPS, its flows learnt from zero", "an XVFI-style multi-scale "
     "flow network trained once on every subject's video (held-out frames excluded) and the synthetic motion "
     "videos of interp_motion_videos, that refines OpenCV's Farneback "
     "flows (interp.flow_init=farneback; zero: XVFI's way)", "no downloaded weights or data; flows learnt from zero "
     "stay a cross-fade within a CPU budget"),
    ("RGBD captures", "ZED2 depth", "the synthetic subjects' rendered depth with Gaussian noise",
     "no depth camera here"),
    ("RGB fit", "free intrinsics", "a fixed principal point (image centre); the root rotation folded into the camera; "
     "the jaw's opening angle kept in fit_rgb.jaw_limits_deg ([-6, 40] degrees); in video mode each frame's "
     "expression under a prior of weight 1e-2 (fit_rgb.video_expression_reg; images mode 1e-4)",
     "stability on short clips; pretraining uses neck/jaw/eyes, the camera carries the root; a fit once turned the "
     "jaw 48 degrees the closed way; at 1e-4 a frame fitted alone wandered in all 50 expression coefficients, and a "
     "clip the avatar never saw got codes unlike its training frames' (experiment log)"),
    ("RGBD fit", "blocks 1-3 as written", "fixed (known) intrinsics and a small L2 prior on shape/expression",
     "a depth camera's intrinsics are known; the prior keeps noisy frames plausible"),
    ("CNeRF rays", "a fixed [near, far]", "each ray sampled inside the head's bounding sphere in camera space; a learned "
     "background feature composited by 1 - opacity", "fitted heads lie at other distances than a fixed interval"),
    ("sizes (tiny)", "8x384 MLP, 64 samples, 32->256 px, batch 64, 310 000 + 2 500 iterations, 1000 fine-tuning "
     "iterations, 4 of 8 layers frozen, neck range [80, 60, 80] deg", "4x96 MLP, 16 samples, 16->128 px, batch 4, "
     "3 000 + 200 iterations, 200 fine-tuning iterations (the final recipe 1 200), 2 of 4 layers frozen (the final "
     "recipe 1), neck range [30, 40, 20] deg",
     "two CPU cores and two hours; `scale=paper` restores the dissertation's sizes"),
    ("speech corpus", "recorded GRID speakers", "GRID-grammar sentences spoken by seven espeak-ng and three Festival "
     "voices, augmented (channel, reverberation, noise, gain); real GRID and Obama clips as a test set and, the scored "
     "clip or speaker left out, for fine-tuning; no MBROLA voices", "no downloads; GRID audio is not redistributable "
     "here; Debian has no MBROLA voices"),
    ("speech targets and metric", "each speaker's landmarks; lip error on them", "seed 000 learns each speaker's "
     "motion placed on Pr(B0) (the utterance's mean shape removed); the lip error is reported raw and on the motion, "
     "beside a still mouth and a phoneme lookup", "its landmarks are Pr(B0) plus viseme offsets and cannot carry a "
     "speaker's face; a raw error would mostly measure the face"),
    ("256² / 512² models", "the chosen recipe trained at 256² and 512² (300 000 iterations each)", "the final "
     "recipe's model continued from the previous resolution with its own strategy (β6)", "the dissertation names "
     "the resolutions and the iterations, not how each one starts"),
    ("avatar weights (tiny, smoke)", "the last iterate of fine-tuning", "the final recipe's avatar is an "
     "exponential moving average of its weights (scale.finetune_final_ema_decay = 0.99; paper scale: the last "
     "iterate)", "at 1 200 iterations the last iterate overfits the training frames; the average scored higher on "
     "both synthetic subjects in every seed (sweeps finetune_ema, finetune_ema_talk)"),
    ("avatar loss (tiny, smoke)", "eq. (8): masked MSE, VGG16 features, offsets", "eq. (8) + 0.02 x the ST-LPIPS "
     "distance (AlexNet, weights in its wheel) on one 64-pixel head window per sample, in the final recipe "
     "(scale.finetune_final_w_st_lpips; paper scale: eq. 8 alone)", "eq. (8)'s renders were blurrier than a copied "
     "training frame; chosen on validation frames. ST-LPIPS is also reported, so identity, landmark error and face "
     "detection stand beside it"),
    ("avatar test split", "INSTA protocol (last 350 frames)", "for multi-clip real subjects the last clip is held out",
     "an avatar must render a recording it never saw"),
]


def substitutions_table() -> "Table":
    table = Table("substitutions", "Substitutions: where this platform differs from the dissertation, and why",
                  ["what", "dissertation", "here", "why"])
    for what, theirs, ours, why in SUBSTITUTIONS:
        table.add(what=what, dissertation=theirs, here=ours, why=why)
    return table
