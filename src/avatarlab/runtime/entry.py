"""What every step's `python -m avatarlab.<stage>` has in common.

    READS = ("seed", "preprocess", "fit_rgb")      # the config sections the step reads

    @entry_point(READS)
    def main(cfg, device): ...

`entry_point` makes `main` a Hydra app over conf/ (so any override or `-m` sweep works), sets seeds, threads and the
device, and hands `main` only the declared sections, resolved: reading any other section fails, so `READS` is the
complete list of settings a step depends on. The workflow reads the same `READS` (without importing the module) and
passes exactly those resolved sections as the step's Snakemake params, so a change to any of them - and to nothing
else - reruns the step. Bad input (a missing or malformed file, a setting of the wrong kind) ends the step with one
line naming the culprit, on stderr and in the log, instead of a traceback.
"""
from __future__ import annotations

import functools
import logging
import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from avatarlab.runtime.config import CONF_DIR, setup_run
from avatarlab.runtime.errors import USER_ERRORS, ConfigError, InputError, InputFileError  # noqa: F401 (re-exported)

log = logging.getLogger("avatarlab")
#: always available to a step: where results go and how it runs (none of these changes a result's numbers)
RUNTIME_KEYS = ("paths", "threads", "device")


def step_settings(cfg: DictConfig, reads: tuple[str, ...]) -> dict:
    """The resolved sections a step reads: plain values, the step's whole dependence on the config."""
    out = {}
    for key in reads:
        if key not in cfg:
            raise ConfigError(f"the config has no section '{key}'")
        value = cfg[key]
        out[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    return out


def step_config(cfg: DictConfig, reads: tuple[str, ...]) -> DictConfig:
    """`cfg` restricted to `reads` + the runtime keys, resolved and read-only (struct: other keys raise)."""
    kept = step_settings(cfg, tuple(k for k in RUNTIME_KEYS if k in cfg) + tuple(reads))
    restricted = OmegaConf.create(kept)
    OmegaConf.set_struct(restricted, True)
    OmegaConf.set_readonly(restricted, True)
    return restricted


def entry_point(reads: tuple[str, ...]):
    def decorate(fn):
        @functools.wraps(fn)
        def main(cfg: DictConfig) -> None:
            from avatarlab.runtime.schema import validate

            try:
                validate(cfg)
                device = setup_run(cfg)
                fn(step_config(cfg, reads), device)
            except USER_ERRORS as err:
                log.error("%s", err)
                print(f"avatarlab error: {err}", file=sys.stderr, flush=True)
                sys.exit(2)

        wrapped = hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")(main)
        wrapped.reads = reads
        return wrapped

    return decorate
