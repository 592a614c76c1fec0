"""The claims table's one rule (report/claims.py): every verdict from (number, claimed side, noise, baselines)."""
from __future__ import annotations

import pytest

from avatarlab.report import claims
from avatarlab.report.claims import RULE, Evidence, mean_difference_noise, verdict
from avatarlab.workflow.layout import ResultsTree


def avatar(subject, init, psnr, baseline=20.0, mouth=None, variant="a", recipe="base"):
    def part(value):
        return {"frames": 6, "model": {"psnr": value}, "baselines": {"last_frame": {"psnr": baseline}},
                "gain": {"psnr": {"best_baseline": "last_frame", "baseline": baseline, "gain": value - baseline}}}

    return {"subject": subject, "init": init, "recipe": recipe, "variant": variant, "seed": 0,
            "eval": {"all": part(psnr), "mouth_open": part(psnr if mouth is None else mouth)}}


@pytest.mark.parametrize("evidence, expected", [
    (Evidence(0.30, noise=0.05), "reproduced"),
    (Evidence(-0.30, noise=0.05), "not reproduced"),
    (Evidence(0.02, noise=0.05), "within noise"),
    (Evidence(-0.05, noise=0.05), "within noise"),  # on the edge: not beyond the noise
    (Evidence(25.0, level=29.0, noise=0.4), "not reproduced"),  # an absolute level, below the claimed one
    (Evidence(0.5, higher=False, noise=0.1), "not reproduced"),  # the claim says lower
    (Evidence(0.30, noise=0.05, beats_baselines=False), "not testable: a model it rests on does not beat its best "
                                                          "trivial baseline"),
    (Evidence(0.30, noise=None), "not testable: no noise estimate"),
    (Evidence(None, noise=0.05), "not testable: this run did not measure it"),
    (Evidence(float("nan"), noise=0.05), "not testable: this run did not measure it"),
    (Evidence(0.30, noise=0.05, untestable="no ZED2 captures"), "not testable: no ZED2 captures"),
])
def test_one_rule_decides_every_verdict(evidence, expected):
    assert verdict(evidence) == expected


def test_a_mixed_sign_family_is_not_reproduced_by_counting_wins():
    """Three tiny alpha2 wins and one 2 dB loss: 75 % of pairs won, but the mean difference is -0.49 dB."""
    base = {}
    for i, (one, two) in enumerate([(26.0, 26.02), (26.0, 26.03), (26.0, 26.01), (26.0, 23.98)]):
        base[("s", f"beta{i + 1}_from_alpha1")] = avatar("s", f"beta{i + 1}_from_alpha1", one, mouth=one)
        base[("s", f"beta{i + 1}_from_alpha2")] = avatar("s", f"beta{i + 1}_from_alpha2", two, mouth=two)
    (row,) = claims.alpha_family_claim(base, threshold=0.05, noise="seed SD")
    assert "3/4 pairs (75 %)" in row["this_run"] and "-0.49 dB" in row["this_run"]
    assert row["verdict"] != "reproduced"
    # the pairs' own spread is the noise of their mean here (CI half-width over 4 pairs ~1.6 dB)
    assert row["verdict"] == "within noise"
    # the same losses with a consistent sign are beyond the noise: not reproduced
    for i in range(4):
        base[("s", f"beta{i + 1}_from_alpha2")] = avatar("s", f"beta{i + 1}_from_alpha2", 25.0, mouth=25.0)
    (row,) = claims.alpha_family_claim(base, threshold=0.05, noise="seed SD")
    assert row["verdict"] == "not reproduced"


def test_a_claim_resting_on_avatars_below_their_baselines_is_not_testable():
    """The smoke case: (c) beats (b) by 0.3 dB, both 12 dB below copying the last frame."""
    avatars = [avatar("synth_talk", "beta6_from_alpha2", 14.0, baseline=26.0, variant="b"),
               avatar("synth_talk", "beta6_from_alpha2", 14.3, baseline=26.0, variant="c")]
    (row,) = claims.interpolation_claim(avatars, "beta6_from_alpha2", threshold=0.05, noise="seed SD")
    assert row["verdict"] == "not testable: a model it rests on does not beat its best trivial baseline"
    assert "+0.30 dB" in row["this_run"] and "(b)" in row["published"]
    above = [avatar("synth_talk", "beta6_from_alpha2", p, baseline=10.0, variant=v) for p, v in ((14.0, "b"),
                                                                                                 (14.3, "c"))]
    assert claims.interpolation_claim(above, "beta6_from_alpha2", 0.05, "")[0]["verdict"] == "reproduced"


def test_the_final_recipe_within_noise_of_the_best_is_within_noise_either_way():
    final = "beta6_from_alpha2"
    ranks = {("s", final): avatar("s", final, 26.00), ("s", "beta2_from_alpha1"): avatar("s", "beta2_from_alpha1",
                                                                                             26.04)}
    (row,) = claims.final_recipe_claim(ranks, final, threshold=0.1, noise="")
    assert row["verdict"] == "within noise" and "rank 2 of 2" in row["this_run"]
    ranks[("s", "beta2_from_alpha1")] = avatar("s", "beta2_from_alpha1", 25.5)
    assert claims.final_recipe_claim(ranks, final, 0.1, "")[0]["verdict"] == "reproduced"
    ranks[("s", "beta2_from_alpha1")] = avatar("s", "beta2_from_alpha1", 27.0)
    assert claims.final_recipe_claim(ranks, final, 0.1, "")[0]["verdict"] == "not reproduced"
    assert claims.final_recipe_claim(ranks, final, None, "")[0]["verdict"] == "not testable: no noise estimate"


def test_the_noise_of_a_mean_of_differences():
    assert mean_difference_noise([0.1], 0.2) == pytest.approx(0.2)
    assert mean_difference_noise([0.1, 0.1, 0.1, 0.1], 0.2) == pytest.approx(0.1)  # 0.2 / sqrt(4), no spread
    assert mean_difference_noise([1.0, -1.0], 0.2) > 5  # the pairs disagree: their CI dominates
    assert mean_difference_noise([0.1], None) is None


def test_the_claims_table_states_its_rule(tmp_path):
    table = claims.claims_table(ResultsTree(tmp_path), [], "beta6_from_alpha2", "smoke")
    assert RULE in table.note
    assert {r["verdict"] for r in table.rows} == {"not testable: the INSTA videos and the other four methods are not "
                                                  "part of this run"}
