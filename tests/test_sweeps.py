"""Sweeps: expansion in Hydra's override grammar, checked sweep files, and the sweep table's statistics."""
from __future__ import annotations

import csv
import json

import pytest

from avatarlab.report.sweep_report import summarise
from avatarlab.runtime.errors import ConfigError
from avatarlab.workflow.sweeps import expand, load_sweep, load_sweeps


def test_expansion_is_hydras_grammar_and_cartesian_product():
    points = expand({"finetune.lr": "1e-4,3e-4", "seed": "range(3)"})
    assert [p.overrides for p in points][:2] == [("finetune.lr=0.0001", "seed=0"), ("finetune.lr=0.0001", "seed=1")]
    assert len(points) == 6 and len({p.name for p in points}) == 6
    assert points[4].values == {"finetune.lr": 0.0003, "seed": 1} and points[4].seed == 1
    assert points[0].setting == points[2].setting != points[3].setting  # seeds of one setting share it
    choice = expand({"model.renderer": "choice(proposed,baseline)"})
    assert [p.overrides for p in choice] == [("model.renderer=proposed",), ("model.renderer=baseline",)]
    lists = expand({"synthetic.neck_deg": "[15,20,10],[60,45,40]"})
    assert [p.values["synthetic.neck_deg"] for p in lists] == [[15, 20, 10], [60, 45, 40]]
    assert [p.name for p in lists] == ["neck_deg-15-20-10", "neck_deg-60-45-40"]
    assert [p.overrides for p in expand({"seed": "range(1,7,3)"})] == [("seed=1",), ("seed=4",)]


def test_the_shipped_sweeps_load():
    sweeps = load_sweeps()
    assert {"finetune_lr", "beta4_pmax", "neck_range", "finetune_ema"} <= set(sweeps)
    ema = sweeps["finetune_ema"]
    assert (ema.recipe, ema.subject, len(ema.points)) == ("final", "synth_turns", 9)
    assert {p.values["finetune.ema_decay"] for p in ema.points} == {0.0, 0.99, 0.997}
    lr = sweeps["finetune_lr"]
    assert lr.step == "finetune" and len(lr.points) == 9 and lr.subject == "synth_talk"
    assert sweeps["beta4_pmax"].parent == "alpha1" and len(sweeps["beta4_pmax"].points) == 6
    distortion = sweeps["finetune_distortion"]
    assert (distortion.recipe, distortion.subject, len(distortion.points)) == ("final", "obama", 9)
    assert {p.values["finetune.w_distortion"] for p in distortion.points} == {0.0, 0.02, 0.1}
    # workflow config sweep_seeds: the seed axis of every sweep that has one, and nothing else
    fewer = load_sweeps(seeds=2)
    assert len(fewer["finetune_lr"].points) == 6 and {p.seed for p in fewer["finetune_lr"].points} == {0, 1}
    assert {p.setting for p in fewer["finetune_lr"].points} == {p.setting for p in lr.points}


@pytest.mark.parametrize("text, message", [
    ("step: train\noverrides: {seed: range(2)}\n", "step must be one of"),
    ("step: finetune\nsubject: s\noverrides: {seed: range(2)}\n", "a finetune sweep needs init"),
    ("step: pretrain\nstrategy: alpha1\noverrides: {seed: 'range(2'}\n", "sweep overrides"),
    ("step: pretrain\nstrategy: alpha1\n", "'overrides' must map"),
])
def test_a_bad_sweep_file_is_named_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_sweep(path)
    assert str(err.value).startswith(str(path)) and message in str(err.value) and "\n" not in str(err.value)


def fake_point(folder, name, psnr, st_lpips):
    part = {"model": {"psnr": psnr, "st_lpips": st_lpips},
            "gain": {"psnr": {"best_baseline": "last_frame", "baseline": 25.0, "gain": psnr - 25.0},
                     "st_lpips": {"best_baseline": "last_frame", "baseline": 0.3, "gain": 0.3 - st_lpips}}}
    (folder / name).mkdir(parents=True)
    (folder / name / "eval.json").write_text(json.dumps({"all": part}))


@pytest.mark.parametrize("metric", ["psnr", "st_lpips"])
def test_sweep_table_orders_by_the_metrics_direction(tmp_path, metric):
    spec = tmp_path / "lr.yaml"
    spec.write_text(f"step: finetune\nsubject: s\ninit: alpha1\nmetric: {metric}\n"
                    "overrides: {finetune.lr: '1e-4,1e-3', seed: range(3)}\n")
    sweep = load_sweep(spec)
    folder = tmp_path / "results"
    for p in sweep.points:  # lr 1e-3: +2 dB and lower ST-LPIPS, with a 0.1 seed-to-seed wobble
        good = p.values["finetune.lr"] == 1e-3
        fake_point(folder, p.name, 26.0 + 2.0 * good + 0.1 * p.seed, 0.25 - 0.05 * good + 0.001 * p.seed)
    table, rows = summarise(sweep, folder)
    best = next(r for r in rows if r["differs_from_best"] == "best")
    assert best["finetune.lr"] == 1e-3 and best["seeds"] == 3
    other = next(r for r in rows if r is not best)
    assert other["differs_from_best"] == "yes" and other["worse_than_best"] > 0
    assert best[f"{metric}_ci95"] > 0
    assert "lower is better" in table.note if metric == "st_lpips" else "higher is better" in table.note


def test_sweep_table_shows_the_also_metrics_beside_the_main_one(tmp_path):
    """`also: [landmark_nme, identity_similarity]`: each setting's mean and CI over its seeds; one never measured is
    'missing', not a number; a malformed list is a one-line error naming the file."""
    spec = tmp_path / "ema.yaml"
    spec.write_text("step: finetune\nsubject: s\ninit: alpha1\nalso: [landmark_nme, identity_similarity, psnr]\n"
                    "overrides: {finetune.ema_decay: '0.0,0.99', seed: range(3)}\n")
    sweep = load_sweep(spec)
    assert sweep.also == ("landmark_nme", "identity_similarity")  # the main metric is not repeated
    folder = tmp_path / "results"
    for p in sweep.points:
        averaged = p.values["finetune.ema_decay"] > 0
        fake_point(folder, p.name, 26.0 + averaged + 0.1 * p.seed, 0.25)
        report = json.loads((folder / p.name / "eval.json").read_text())
        report["all"]["model"].update(landmark_nme=0.07 + 0.01 * averaged + 0.001 * p.seed, identity_similarity=None)
        (folder / p.name / "eval.json").write_text(json.dumps(report))
    table, rows = summarise(sweep, folder)
    by_decay = {r["finetune.ema_decay"]: r for r in rows}
    assert by_decay[0.99]["landmark_nme"] == pytest.approx(0.081) and by_decay[0.0]["landmark_nme"] == pytest.approx(0.071)
    assert by_decay[0.0]["landmark_nme_ci95"] == pytest.approx(4.303 * 0.001 / 3 ** 0.5, rel=1e-3)
    assert by_decay[0.0]["identity_similarity"] == "missing" and by_decay[0.0]["identity_similarity_ci95"] is None
    assert table.columns[-4:] == ["landmark_nme", "landmark_nme_ci95", "identity_similarity",
                                  "identity_similarity_ci95"]
    assert "landmark_nme, identity_similarity" in table.note and "| missing |" in table.markdown()
    spec.write_text("step: finetune\nsubject: s\ninit: alpha1\nalso: landmark_nme\noverrides: {seed: range(2)}\n")
    with pytest.raises(ConfigError, match="'also' must be a list of metric names") as err:
        load_sweep(spec)
    assert str(err.value).startswith(str(spec))


def test_sweep_table_reads_only_the_seeds_the_workflow_ran(tmp_path):
    """workflow config sweep_seeds=2: the table step gets --seeds 2 and reads seeds 0 and 1 only (no seed-2 points)."""
    from avatarlab.report.sweep_report import main

    spec = tmp_path / "lr.yaml"
    spec.write_text("step: finetune\nsubject: s\ninit: alpha1\noverrides: {finetune.lr: '1e-4,1e-3', seed: range(3)}\n")
    folder = tmp_path / "results"
    for p in load_sweep(spec, seeds=2).points:
        fake_point(folder, p.name, 26.0 + p.seed, 0.25)
    assert main(["--sweep", str(spec), "--dir", str(folder), "--seeds", "2"]) == 0
    with open(folder / "table.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["seeds"] for r in rows] == ["2", "2"] and [float(r["psnr"]) for r in rows] == [26.5, 26.5]
    with pytest.raises(FileNotFoundError):  # the file's three seeds: seed 2 was never run
        main(["--sweep", str(spec), "--dir", str(folder)])


def test_a_far_baseline_does_not_flatten_the_sweeps_points():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from avatarlab.report.sweep_report import baseline_line

    fig, (near, far) = plt.subplots(1, 2)
    points = [22.40, 22.45, 22.50]
    for ax in (near, far):
        ax.plot([0, 1, 2], points)
    baseline_line(near, 22.3, "last_frame", points)
    baseline_line(far, 34.0, "last_frame", points)
    assert near.get_ylim()[1] - near.get_ylim()[0] < 1 and any(line.get_ydata()[0] == 22.3 for line in near.lines[1:])
    low, high = far.get_ylim()
    assert high - low < 0.2 and high < 34.0, "the axis keeps to the points"
    assert any("34.00 above" in t.get_text() for t in far.texts)
    plt.close(fig)


def test_a_sweep_chooses_on_validation_and_the_test_only_scores(tmp_path):
    """The setting marked `chosen` is the one with the best validation PSNR (train.json), even where another scores
    better on the test frames; without validation scores nothing is chosen and the note says so."""
    spec = tmp_path / "ema.yaml"
    spec.write_text("step: finetune\nsubject: s\ninit: alpha1\noverrides: {finetune.ema_decay: '0.0,0.99', seed: range(2)}\n")
    sweep = load_sweep(spec)
    folder = tmp_path / "results"
    for p in sweep.points:
        averaged = p.values["finetune.ema_decay"] > 0
        fake_point(folder, p.name, 26.0 + (0.0 if averaged else 1.0) + 0.1 * p.seed, 0.25)
    table, rows = summarise(sweep, folder)
    assert all(r["chosen"] == "" and r["validation_psnr"] is None for r in rows)
    assert "chooses nothing" in table.note
    for p in sweep.points:
        averaged = p.values["finetune.ema_decay"] > 0
        (folder / p.name / "train.json").write_text(json.dumps({"validation_psnr": 24.0 + averaged + 0.01 * p.seed}))
    table, rows = summarise(sweep, folder)
    chosen = [r for r in rows if r["chosen"] == "chosen"]
    assert len(chosen) == 1 and chosen[0]["finetune.ema_decay"] == 0.99
    assert chosen[0]["validation_psnr"] == pytest.approx(25.005)
    assert chosen[0]["differs_from_best"] != "best"  # the test's best is the other one: a score, not the choice
    assert "best mean validation PSNR" in table.note and "| chosen |" in table.markdown()
    from avatarlab.report.sweep_report import validation_scores

    point = folder / sweep.points[0].name  # a train.json with the scores only: the chosen step's
    (point / "train.json").write_text(json.dumps({"chosen_step": 300, "validation_scores": [
        {"step": 300, "psnr": 22.4}, {"step": 600, "psnr": 22.1}]}))
    assert validation_scores(point)["psnr"] == 22.4


def test_a_sweep_may_choose_on_validation_st_lpips(tmp_path):
    """`choose_on: st_lpips` (the perceptual-term sweep): the setting with the lowest mean validation ST-LPIPS is
    chosen, even where another has the better validation PSNR; a word other than psnr / st_lpips is refused."""
    spec = tmp_path / "perceptual.yaml"
    spec.write_text("step: finetune\nsubject: s\ninit: alpha1\nchoose_on: st_lpips\n"
                    "overrides: {finetune.perceptual: 'features,st_lpips', seed: range(2)}\n")
    sweep = load_sweep(spec)
    assert sweep.choose_on == "st_lpips"
    folder = tmp_path / "results"
    for p in sweep.points:
        sharp = p.values["finetune.perceptual"] == "st_lpips"
        fake_point(folder, p.name, 26.0 + 0.1 * p.seed, 0.25)
        (folder / p.name / "train.json").write_text(json.dumps(
            {"validation_psnr": 24.0 - 0.2 * sharp, "validation_st_lpips": 0.17 if sharp else 0.24 + 0.01 * p.seed}))
    table, rows = summarise(sweep, folder)
    chosen = [r for r in rows if r["chosen"] == "chosen"]
    assert len(chosen) == 1 and chosen[0]["finetune.perceptual"] == "st_lpips"
    assert chosen[0]["validation_st_lpips"] == pytest.approx(0.17)
    other = next(r for r in rows if r is not chosen[0])
    assert other["validation_st_lpips"] == pytest.approx(0.245) and other["validation_psnr"] == pytest.approx(24.0)
    assert "best mean validation ST-LPIPS" in table.note and "validation_st_lpips" in table.markdown()
    spec.write_text(spec.read_text().replace("choose_on: st_lpips", "choose_on: ssim"))
    with pytest.raises(ConfigError, match=r"perceptual.yaml: choose_on must be one of psnr, st_lpips"):
        load_sweep(spec)
