"""Commands a person can live with: the scale chosen once and said at the start of every call."""
from __future__ import annotations

import pytest
from helpers import REPO, run_snakemake
from helpers.workflow import jobs_planned

from avatarlab.workflow.steps import SCALE_FILE, chosen_scale


def test_the_scale_is_the_given_one_else_the_remembered_one_else_tiny(tmp_path):
    said = []
    assert chosen_scale(None, tmp_path, said.append) == "tiny"
    (tmp_path / SCALE_FILE).write_text("smoke\n")
    assert chosen_scale(None, tmp_path, said.append) == "smoke"
    assert chosen_scale("paper", tmp_path, said.append) == "paper"
    assert said == ["avatarlab: scale tiny (the default)", f"avatarlab: scale smoke (remembered in {SCALE_FILE})",
                    "avatarlab: scale paper (given)"]
    (tmp_path / SCALE_FILE).write_text("huge\n")
    with pytest.raises(ValueError, match=f"scale 'huge' \\(remembered in {SCALE_FILE}\\): expected one of smoke"):
        chosen_scale(None, tmp_path, said.append)


def test_make_main_remembers_the_scale_for_later_make_and_snakemake_calls(tmp_path):
    import subprocess

    dry = subprocess.run(["make", "-n", "-C", str(REPO), "main", "SCALE=smoke"], capture_output=True, text=True)
    assert 'echo "smoke" > .avatarlab-scale' in dry.stdout and "--config scale=smoke" in dry.stdout
    (tmp_path / SCALE_FILE).write_text("smoke\n")
    out = run_snakemake(tmp_path, "-n", "--cores", "2")  # no --config scale: the remembered one
    assert "avatarlab: scale smoke (remembered in .avatarlab-scale)" in out.stderr
    planned = jobs_planned(out)
    assert planned["pretrain_alpha"] == 2 and "results/smoke/pretrain/alpha1/model.pt" in out.stdout + out.stderr


def test_the_quiet_console_prints_a_line_per_step_and_a_failed_steps_log(tmp_path):
    """`--logger avatarlab` (what `make main` uses): a line per finished step with the count and an estimate of the
    time left; a failed step's rule, log path and last log lines; nothing of Snakemake's job blocks."""
    import re

    import cv2
    import numpy as np

    out = run_snakemake(tmp_path, "--logger", "avatarlab", "--cores", "2", "results/smoke/headmodel/render_grid.png",
                        "results/smoke/subjects/synth_talk/frames.json", "--config", "scale=smoke")
    lines = [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]
    steps = [line for line in lines if re.match(r"\[\d+:\d\d:\d\d\] \d of 3 steps done \(\w+\); about \d+:\d\d:\d\d "
                                                  r"left$", line)]
    assert len(steps) == 3 and "avatarlab: 3 steps to run" in lines and len(lines) <= 10, lines
    assert not [line for line in lines if line.startswith(("rule ", "    jobid", "Select jobs"))]
    images = tmp_path / "tiny_images"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((1, 1, 3), np.uint8))
    failed = run_snakemake(tmp_path, "--logger", "avatarlab", "--cores", "1", "results/smoke/subjects/bad/frames.json",
                           "--config", "scale=smoke", f"subjects={{bad: {{source: images, path: {images}}}}}",
                           check=False)
    text = failed.stdout + failed.stderr
    assert failed.returncode != 0
    assert "FAILED: step extract_frames (job 0); its log: logs/smoke/subjects/bad/frames.log" in text
    assert f"    avatarlab error: {images / 'a.png'}: the image is 1x1 pixels" in text


def test_add_subject_checks_the_subject_writes_it_and_the_workflow_plans_it(tmp_path, monkeypatch, capsys):
    import shutil

    from avatarlab import cli

    clip = next((p for p in (REPO.parent / "shared" / "data" / "obama").glob("*.mp4")), None) if (
        REPO.parent / "shared" / "data" / "obama").is_dir() else None
    video = tmp_path / "me.mp4"
    if clip is not None:
        shutil.copy(clip, video)
    else:
        video.write_bytes(b"")  # planning looks at names only
    monkeypatch.setattr(cli, "LOCAL_SUBJECTS", tmp_path / "avatarlab.subjects.yaml")
    monkeypatch.setattr(cli, "scale_of", lambda given: "smoke")
    assert cli.main(["add-subject", "me", str(video), "--fps", "2"]) == 0
    out = capsys.readouterr().out
    assert "results/smoke/avatars/me/final/beta6_from_alpha2/eval.json" in out
    written = (tmp_path / "avatarlab.subjects.yaml").read_text()
    assert f"path: {video}" in written and "source: video" in written and "fps: 2.0" in written
    assert cli.main(["add-subject", "portraits", str(video)]) == 2, "the real image set's name is refused"
    assert cli.main(["add-subject", "me2", str(tmp_path / "nothere.mp4")]) == 2
    assert cli.main(["add-subject", "bad name", str(video)]) == 2
    assert "portraits" not in (tmp_path / "avatarlab.subjects.yaml").read_text(), "a refused subject is not written"
    planned = run_snakemake(tmp_path, "-n", "--cores", "2", "results/smoke/avatars/me/final/beta6_from_alpha2/eval.json",
                            "--config", "scale=smoke")
    counts = jobs_planned(planned)
    assert counts["extract_frames"] >= 1 and counts["evaluate_avatar"] == 1 and counts["finetune_avatar"] == 1, counts
    # the shared steps (the interpolator, the control figures) read the shared subjects only: adding one reruns neither
    shared = run_snakemake(tmp_path, "-n", "--cores", "2", "results/smoke/interp/model.pt",
                           "results/smoke/pretrain/controls/fig30_jaw.json", "--config", "scale=smoke")
    text = shared.stdout + shared.stderr
    for rule in ("train_interpolator", "control_figure"):
        blocks = [b for b in text.split("\nrule ")[1:] if b.startswith(rule + ":")]
        assert blocks and all("subjects/me/" not in b.split("output:")[0] for b in blocks), rule


def test_status_says_what_would_run_and_why(tmp_path, monkeypatch, capsys):
    from avatarlab import cli

    monkeypatch.setattr(cli, "scale_of", lambda given: "smoke")
    monkeypatch.setattr(cli, "WORKDIR", tmp_path)  # a scratch work folder: nothing done yet
    assert cli.main(["status"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("scale smoke: ") and lines[0].endswith(" steps would run")
    assert any(line.split()[0] == "pretrain_alpha" and "2 x Missing output files" in line for line in lines[1:])
