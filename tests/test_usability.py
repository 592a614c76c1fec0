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
