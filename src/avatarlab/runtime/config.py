"""Hydra plumbing shared by every entry point: where conf/ is, and the common run set-up."""
from __future__ import annotations

import logging
import random
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig

if TYPE_CHECKING:  # torch is imported where it is used: the Snakefile reads CONF_DIR and must start fast
    import torch

CONF_DIR = Path(__file__).resolve().parents[3] / "conf"
log = logging.getLogger("avatarlab")


def __getattr__(name: str):
    """`CPU`: the default device of functions that take one (made on first use, so importing this is torch-free)."""
    if name == "CPU":
        import torch

        return torch.device("cpu")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def resolve_device(cfg: DictConfig) -> torch.device:
    """`device` of the config: cpu | cuda | cuda:N | auto (CUDA when available, else the CPU)."""
    import torch

    name = str(cfg.get("device", "cpu"))
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"device={name} requested but CUDA is not available on this machine (use device=auto)")
    return torch.device(name)


def autocast(device: torch.device, enabled: bool):
    """Mixed precision (`amp: true`): float16 on CUDA (with a GradScaler), bfloat16 on the CPU."""
    import torch

    return torch.autocast(device.type, dtype=torch.float16 if device.type == "cuda" else torch.bfloat16,
                          enabled=enabled)


def grad_scaler(device: torch.device, enabled: bool) -> torch.amp.GradScaler:
    """Loss scaling for float16 on CUDA; a pass-through elsewhere (bfloat16 on the CPU needs none)."""
    import torch

    return torch.amp.GradScaler(device.type, enabled=enabled and device.type == "cuda")


def setup_run(cfg: DictConfig) -> torch.device:
    """Seeds, threads and device from the config (every entry point calls this first)."""
    import numpy as np
    import torch

    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(int(cfg.threads))
    device = resolve_device(cfg)
    log.info("scale=%s device=%s threads=%d", cfg.scale.name, device, cfg.threads)
    return device
