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
