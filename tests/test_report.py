"""The report's statistics: means with 95 % CIs over seeds, paired alpha1/alpha2 differences and the noise verdicts,
from eval.json files laid out as the workflow writes them."""
from __future__ import annotations

import json
import math

import pytest

from avatarlab.metrics.seeds import gain_verdict, mean_ci, paired_difference, pooled_sd, single_run_threshold
from avatarlab.report.build import build


def test_mean_ci_is_students_t():
    mean, half, n = mean_ci([1.0, 2.0, 3.0])
    assert (mean, n) == (2.0, 3)
    assert half == pytest.approx(4.302653 * 1.0 / math.sqrt(3), rel=1e-5)  # t(0.975, 2) * sd / sqrt(n)
    assert mean_ci([5.0]) == (5.0, None, 1) and mean_ci([]) == (None, None, 0)


def test_paired_difference_verdicts():
    a = {0: 20.0, 1: 21.0, 2: 22.0}
    assert paired_difference(a, {k: v + 1.0 + 0.01 * k for k, v in a.items()})["exceeds_noise"] is True
    within = paired_difference(a, {0: 20.5, 1: 20.6, 2: 22.1})  # differences +0.5, -0.4, +0.1
    assert within["exceeds_noise"] is False and within["verdict"] == "within the seed-to-seed noise"
    assert paired_difference({0: 1.0}, {0: 2.0})["exceeds_noise"] is None


def test_a_gain_is_better_or_worse_only_beyond_its_ci():
    assert gain_verdict(0.5, 0.4, "frames'") == "better" and gain_verdict(-0.5, 0.4, "clips'") == "worse"
    assert gain_verdict(0.3, 0.4, "frames'") == "within the frames' spread"
    assert gain_verdict(-0.4, 0.4, "clips'") == "within the clips' spread"  # a CI touching zero does not exclude it
    assert gain_verdict(0.5, None, "clips'") is None and gain_verdict(None, None, "clips'") is None


def test_pooled_sd_and_single_run_threshold():
    sd, dof = pooled_sd([[1.0, 3.0], [10.0, 10.0, 10.0], [7.0]])
    assert dof == 3 and sd == pytest.approx(math.sqrt(2.0 / 3))
    assert single_run_threshold(1.0) == pytest.approx(2.7719, abs=1e-3) and single_run_threshold(None) is None


def write_avatar(results, subject, recipe, folder, init, psnr, seed_note=""):
    d = results / "avatars" / subject / recipe / folder
    d.mkdir(parents=True)
    part = {"frames": 6, "model": {"psnr": psnr, "ssim": 0.8, "st_lpips": 0.3},
            "baselines": {"last_frame": {"psnr": 25.0, "ssim": 0.85, "st_lpips": 0.2}},
            "gain": {"psnr": {"best_baseline": "last_frame", "baseline": 25.0, "gain": psnr - 25.0,
                              "beats": psnr > 25.0}}}
    (d / "eval.json").write_text(json.dumps({"init": init, "frames_variant": "a", "all": part, "mouth_open": part,
                                             "split": "last_frames", "render_seconds_per_frame": 0.01, "curve": []}))
    (d / "train.json").write_text(json.dumps({"train_seconds": 10.0, "iterations": 5}))


def test_report_tables_show_seed_means_cis_and_verdicts(tmp_path):
    results = tmp_path / "results"
    final = "beta6_from_alpha2"
    for k, (a1, a2, f) in enumerate([(26.0, 27.0, 26.5), (26.2, 27.1, 26.7), (25.9, 27.05, 26.3)]):
        suffix = f"_seed{k}" if k else ""
        write_avatar(results, "synth_talk", "base", f"alpha1{suffix}", "alpha1", a1)
        write_avatar(results, "synth_talk", "base", f"alpha2{suffix}", "alpha2", a2)
        write_avatar(results, "synth_talk", "final", f"{final}{suffix}", final, f)
    for i, psnr in enumerate([26.0, 26.05, 24.0]):
        write_avatar(results, "synth_talk", "base", f"beta{i + 1}_from_alpha1", f"beta{i + 1}_from_alpha1", psnr)
    write_avatar(results, "synth_talk", "base", final, final, 26.1)
    write_avatar(results, "synth_turns", "base", final, final, 20.0)  # an interpolation subject: no beta ranking
    out = tmp_path / "report"
    summary = build(results, out, final, "smoke")
    assert summary["rows"]["final_avatars"] == 1 and summary["rows"]["alpha1_vs_alpha2"] == 4
    finals = (out / "tables" / "final_avatars.csv").read_text().splitlines()
    header, row = finals[0].split(","), dict(zip(finals[0].split(","), finals[1].split(",")))
    assert "psnr_ci95" in header and row["seeds"] == "3"
    assert float(row["psnr"]) == pytest.approx(26.5) and float(row["psnr_ci95"]) == pytest.approx(
        4.302653 * 0.2 / math.sqrt(3), rel=1e-4)
    paired = (out / "tables" / "alpha_paired.md").read_text()
    assert "| synth_talk | all | psnr | 3 | 1.02 |" in paired and "exceeds the seed-to-seed noise" in paired
    assert "1.0166" in (out / "tables" / "alpha_paired.csv").read_text()  # the CSV keeps every digit
    beta = (out / "tables" / "beta_ablation.csv").read_text()
    assert "no (within noise)" in beta and ",yes" in beta  # 0.05 dB apart vs 2.0 dB below the best
    stage2 = (out / "tables" / "stage2_comparisons.csv").read_text()
    # beta3 (24.0) vs beta1 (26.0) from alpha1: -2 dB, beyond the noise; beta1 vs alpha1 (seed 0: 26.0): 0, within
    assert "synthetic share 0.25 (beta3 vs beta1),-2.0,-2.0,worse" in stage2
    assert "continuing on real images (beta1 vs its alpha),0.0,0.0,within noise" in stage2
    readme = (out / "README.md").read_text()
    assert "alpha2 minus alpha1, paired by seed" in readme
    claims = (out / "tables" / "claims.md").read_text()
    # beta6 (26.10 dB) is first but only 0.05 dB above beta2: within the seed noise (pooled SD ~0.15 dB)
    assert "margin +0.05 dB) | best trivial baseline 25.00 dB |" in claims and "| within noise |" in claims
    assert "synth_talk: beta6_from_alpha2 26.10 dB" in claims
    assert "rank 1 of 4" in claims and "synth_turns: beta6" not in claims and "20.00 dB" not in claims
    assert "not testable: the INSTA videos" in claims


def test_the_method_doc_lists_every_substitution_of_the_report():
    from pathlib import Path

    from avatarlab.report.build import SUBSTITUTIONS

    readme = (Path(__file__).resolve().parents[1] / "docs" / "method.md").read_text()
    for what, theirs, ours, why in SUBSTITUTIONS:
        assert f"| {what} | {theirs} | {ours} | {why} |" in readme, what


def test_the_tiny_sizes_substitution_states_tinys_config():
    """The 'sizes (tiny)' row is prose; it must say what conf/scale/tiny.yaml sets, so it cannot go stale."""
    from pathlib import Path

    import yaml

    from avatarlab.report.build import SUBSTITUTIONS

    tiny = yaml.safe_load((Path(__file__).resolve().parents[1] / "conf/scale/tiny.yaml").read_text())
    row = next(ours for what, _, ours, _ in SUBSTITUTIONS if what == "sizes (tiny)")

    def n(value: int) -> str:
        return f"{value:,}".replace(",", " ")

    for part in (f"{tiny['nerf_depth']}x{tiny['nerf_width']} MLP", f"{tiny['nerf_samples']} samples",
                 f"{tiny['pretrain_feature_size']}->{tiny['pretrain_image_size']} px", f"batch {tiny['pretrain_batch']}",
                 f"{n(tiny['pretrain_alpha_iterations'])} + {n(tiny['pretrain_beta_iterations'])} iterations",
                 f"{n(tiny['finetune_iterations'])} fine-tuning iterations (the final recipe "
                 f"{n(tiny['finetune_final_iterations'])})",
                 f"{tiny['finetune_freeze_layers']} of {tiny['nerf_depth']} layers frozen (the final recipe "
                 f"{tiny['finetune_final_freeze_layers']})",
                 "neck range [" + ", ".join(str(v) for v in tiny["synthetic_neck_deg"]) + "] deg"):
        assert part in row, part


def test_the_weight_averaging_substitution_states_the_configured_decays():
    """The row names tiny's decay, and paper scale keeps the dissertation's last iterate (decay 0)."""
    from helpers import compose_config

    from avatarlab.report.build import SUBSTITUTIONS

    decay = {name: compose_config([f"scale={name}"]).scale.finetune_final_ema_decay  # smoke, paper inherit tiny's
             for name in ("smoke", "tiny", "paper")}
    assert decay["paper"] == 0 and decay["tiny"] > 0 and decay["smoke"] == decay["tiny"]
    row = next(ours for what, _, ours, _ in SUBSTITUTIONS if what == "avatar weights (tiny, smoke)")
    assert f"scale.finetune_final_ema_decay = {decay['tiny']:g}" in row


def test_the_rgb_fit_substitution_states_the_configured_jaw_limits():
    from pathlib import Path

    import yaml

    from avatarlab.report.build import SUBSTITUTIONS

    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "conf/config.yaml").read_text())
    low, high = config["fit_rgb"]["jaw_limits_deg"]
    row = next(ours for what, _, ours, _ in SUBSTITUTIONS if what == "RGB fit")
    assert f"fit_rgb.jaw_limits_deg ([{low:g}, {high:g}] degrees)" in row


def test_figure_rows_and_columns_are_labelled_and_readable():
    import numpy as np

    from avatarlab.report.figures import labelled_grid

    rows = [(name, np.full((32, 32 * 4, 3), value, np.uint8)) for name, value in
            (("truth", 40), ("avatar", 120), ("best baseline: nearest", 200))]
    image = labelled_grid(rows, [f"test frame {i}" for i in (8, 9, 10, 11)])
    cell = 32 * 5  # enlarged to at least 160 px
    assert image.shape == (28 + 3 * cell, 150 + 4 * cell, 3)
    assert (image[28 + cell // 2, 150 + 10] == 40).all() and (image[28 + cell + 5, 150 + 10] == 120).all() and (image[28 + 2 * cell + 5, 150 + 3 * cell + 5] == 200).all()
    assert (image[28:, :150] < 128).any() and (image[:28, 150:] < 128).any(), "row and column labels are drawn"


def test_the_time_vs_quality_figure_marks_where_the_avatar_gets_sharper_than_a_copied_frame(tmp_path):
    """Figures 57-58 with a third panel: ST-LPIPS of the snapshots against time, the nearest training frame's as a
    line, and the first snapshot below it."""
    from PIL import Image

    from avatarlab.report.figures import first_below, quality_figures

    curve = [{"step": 100 * k, "seconds": 10.0 * k, "psnr": 20 + k, "ssim": 0.8, "st_lpips": 0.4 - 0.05 * k}
             for k in range(1, 6)]
    assert first_below(curve, "st_lpips", 0.22)["seconds"] == 40.0
    assert first_below(curve, "st_lpips", 0.1) is None and first_below([{"st_lpips": None}], "st_lpips", 1.0) is None
    scores = {"psnr": 24.0, "ssim": 0.8, "st_lpips": 0.15}
    baselines = {"nearest": {"psnr": 22.0, "ssim": 0.7, "st_lpips": 0.22},
                 "mean_frame": {"psnr": 21.0, "ssim": 0.75, "st_lpips": 0.3}}
    avatar = {"subject": "s", "recipe": "final", "init": "beta6_from_alpha2", "variant": "a", "seed": 0,
              "eval": {"curve": curve, "all": {"model": scores, "baselines": baselines},
                       "render_seconds_per_frame": 0.1}}
    written = quality_figures([avatar], "beta6_from_alpha2", tmp_path)
    figure = Image.open(tmp_path / "time_vs_quality.png")
    assert tmp_path / "time_vs_quality.png" in written and figure.size[0] > 2.5 * figure.size[1]  # three panels
