"""Readers of a preprocessed subject's files, shared by every stage after preprocessing."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np


def load_frame_stack(subject_dir: Path) -> tuple[np.ndarray, dict]:
    """The frames (N, H, W, 3) RGB uint8 and frames.json of a preprocessed subject."""
    meta = json.loads((subject_dir / "frames.json").read_text())
    frames = [cv2.cvtColor(cv2.imread(str(subject_dir / "frames" / f)), cv2.COLOR_BGR2RGB) for f in meta["files"]]
    return np.stack(frames), meta
