"""Killing a training run part-way, as an interrupt would, to test that it resumes."""
from __future__ import annotations

import contextlib

import pytest
import torch


@contextlib.contextmanager
def killed_at_optimizer_step(monkeypatch, n: int):
    """The block must stop with the KeyboardInterrupt raised at the n-th Adam step; Adam is itself again after it."""
    real_step = torch.optim.Adam.step
    calls = {"n": 0}

    def dying_step(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt("killed")
        return real_step(self, *a, **k)

    monkeypatch.setattr(torch.optim.Adam, "step", dying_step)
    try:
        with pytest.raises(KeyboardInterrupt):
            yield
    finally:
        monkeypatch.setattr(torch.optim.Adam, "step", real_step)
