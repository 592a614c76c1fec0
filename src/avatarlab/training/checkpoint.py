"""Training checkpoints that resume only the work they belong to.

A checkpoint carries the fingerprint of its run - resolved settings, code digest, digests of the data files and the
parent model (provenance.fingerprint) - and is resumed only by a run with the same fingerprint; anything else starts
from iteration 0 with a log line saying why. A finished step deletes its checkpoint after writing its model, so a
rerun (`--forcerun`, changed code or data) always trains. Contents are tensors and plain values, read with
`torch.load(weights_only=True)`.
"""
from __future__ import annotations

import logging
from pathlib import Path

import torch

from avatarlab.runtime.io import atomic_path
from avatarlab.runtime.safe_load import load_tensors

log = logging.getLogger(__name__)


class Checkpoint:
    def __init__(self, path: str | Path, fingerprint: str):
        self.path, self.fingerprint = Path(path), fingerprint

    def load(self) -> dict | None:
        """The saved state if it belongs to this work, else None."""
        if not self.path.is_file():
            return None
        state = load_tensors(self.path, "a training checkpoint")
        if not isinstance(state, dict) or state.get("fingerprint") != self.fingerprint:
            log.warning("%s belongs to other settings, code or data: training starts at iteration 0", self.path)
            return None
        log.info("resuming from %s at iteration %d", self.path, state["step"])
        return state

    def save(self, state: dict) -> None:
        with atomic_path(self.path) as tmp:
            torch.save({**state, "fingerprint": self.fingerprint}, tmp)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
