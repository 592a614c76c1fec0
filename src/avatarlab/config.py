"""Hydra plumbing shared by every entry point: where conf/ is, and the common run set-up."""
from __future__ import annotations

import logging
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
log = logging.getLogger("avatarlab")


def setup_run(cfg: DictConfig) -> torch.device:
    """Seeds, threads and device from the config (every entry point calls this first)."""
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(int(cfg.threads))
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("device=cuda requested but CUDA is not available on this machine")
    log.info("scale=%s device=%s threads=%d", cfg.scale.name, cfg.device, cfg.threads)
    return torch.device(cfg.device)
