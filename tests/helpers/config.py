"""Hydra configs for tests, composed from the repository's conf/."""
from __future__ import annotations

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from avatarlab.runtime.config import CONF_DIR


def compose_config(overrides: list[str] | None = None):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides or [])


def step_cfg(module, overrides: list[str] | None = None):
    """The config a step's main() receives: composed, then restricted to the module's READS."""
    from avatarlab.runtime.entry import step_config

    return step_config(compose_config(overrides), module.READS)


def interp_config(**extra):
    """A small interpolation-training config (8 channels, 2 scales, 6 steps of batch 2, checkpoints every 3)."""
    return OmegaConf.create({"seed": 0, "interp": {"width": 8, "scales": 2, "flow_init": "farneback",
                                                   "keep_unwarped": True, "loss": "l1", "lr": 1e-3, "batch": 2,
                                                   "iterations": 6, "checkpoint_every": 3}, **extra})
