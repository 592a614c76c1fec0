"""Probability of a synthetic training sample (seed 002, eq. 9) and the strategies' iteration counts per scale."""
from __future__ import annotations

from dataclasses import dataclass

PAPER_ALPHA_ITERATIONS = 310_000
PAPER_BETA_ITERATIONS = 2_500


def synthetic_probability(n: int, M: int, N: int, p_min: float, p_max: float) -> float:
    """Eq. (9): p(n) = 1 for n <= M, else (1 - (n - M) / (N - M)) (p_max - p_min) + p_min."""
    if n <= M or N <= M:
        return 1.0
    frac = min(max((n - M) / (N - M), 0.0), 1.0)
    return (1.0 - frac) * (p_max - p_min) + p_min


@dataclass(frozen=True)
class Schedule:
    M: int
    N: int
    p_min: float
    p_max: float
    mouth_from: int | None  # iteration from which the mouth-interior head renders the synthetic samples (alpha2)

    def probability(self, n: int) -> float:
        return synthetic_probability(n, self.M, self.N, self.p_min, self.p_max)


def scaled_schedule(strategy, alpha_iterations: int, beta_iterations: int) -> Schedule:
    """A strategy's paper M, N (and alpha2's mouth phase) mapped to this scale's iteration budget:
    the alpha part scales with alpha_iterations / 310000, the beta continuation with beta_iterations / 2500."""
    scale_a = alpha_iterations / PAPER_ALPHA_ITERATIONS
    scale_b = beta_iterations / PAPER_BETA_ITERATIONS
    M = round(strategy["M"] * scale_a)
    N = M + round((strategy["N"] - strategy["M"]) * scale_b)
    mouth = strategy.get("mouth_from")
    if mouth is not None:  # keep at least one mouth-interior iteration however small the scale
        mouth = min(round(mouth * scale_a), M - 1)
    return Schedule(M=M, N=N, p_min=float(strategy["p_min"]), p_max=float(strategy["p_max"]), mouth_from=mouth)
