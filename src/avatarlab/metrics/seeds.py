"""Seed-to-seed noise: means with 95 % confidence intervals over seeds, paired differences between two settings run
with the same seeds, and whether a difference between single runs exceeds the measured seed-to-seed spread.

A difference is called a difference only when it exceeds that noise: for paired seeded runs, when the 95 % CI of
the mean paired difference excludes zero (Student's t); for two single runs, when it is larger than 1.96 * sqrt(2)
times the pooled seed-to-seed standard deviation (the 95 % range of the difference of two runs with that spread).
"""
from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from scipy import stats

LEVEL = 0.95


def mean_ci(values: Iterable[float], level: float = LEVEL) -> tuple[float | None, float | None, int]:
    """(mean, half-width of the `level` CI (None below two values), n) of the finite values."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return None, None, 0
    if v.size == 1:
        return float(v[0]), None, 1
    half = stats.t.ppf(0.5 + level / 2, v.size - 1) * v.std(ddof=1) / math.sqrt(v.size)
    return float(v.mean()), float(half), int(v.size)


def gain_verdict(mean: float | None, half: float | None, spread: str) -> str | None:
    """'better' when a gain's CI (mean ± half) lies wholly above zero, 'worse' when wholly below, otherwise 'within
    the <spread> spread' (e.g. spread="frames'"); None without a CI (fewer than two values)."""
    if mean is None or half is None:
        return None
    return "better" if mean - half > 0 else "worse" if mean + half < 0 else f"within the {spread} spread"


def signed_range(values: Iterable[float]) -> str:
    """'+0.04 to +0.10': the smallest and the largest of signed values (e.g. a gain over seeds)."""
    v = list(values)
    return f"{min(v):+.2f} to {max(v):+.2f}"


def paired_difference(a: dict[int, float], b: dict[int, float], level: float = LEVEL) -> dict:
    """b - a over the seeds both have: mean, CI half-width, n and the verdict."""
    seeds = sorted(set(a) & set(b))
    mean, half, n = mean_ci([b[s] - a[s] for s in seeds], level)
    if n < 2:
        verdict = "one seed only: no noise estimate"
        exceeds = None
    else:
        exceeds = abs(mean) > half
        verdict = ("exceeds the seed-to-seed noise" if exceeds else "within the seed-to-seed noise")
    return {"n": n, "mean": mean, "ci95": half, "exceeds_noise": exceeds, "verdict": verdict}


def pooled_sd(groups: Iterable[Iterable[float]]) -> tuple[float | None, int]:
    """Pooled within-group standard deviation over groups of repeated runs (seeds), and its degrees of freedom."""
    ss, dof = 0.0, 0
    for g in groups:
        v = np.array([x for x in g if x is not None and math.isfinite(x)], dtype=float)
        if v.size >= 2:
            ss += float(((v - v.mean()) ** 2).sum())
            dof += v.size - 1
    return (math.sqrt(ss / dof), dof) if dof else (None, 0)


def single_run_threshold(sd: float | None) -> float | None:
    """The smallest difference between two single runs that exceeds seed noise of standard deviation `sd`."""
    return None if sd is None else 1.96 * math.sqrt(2.0) * sd
