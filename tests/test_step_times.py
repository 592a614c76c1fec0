"""The per-rule job times read from a Snakemake log (avatarlab.workflow.step_times)."""
from __future__ import annotations

import pytest

from avatarlab.runtime.errors import ConfigError
from avatarlab.workflow.step_times import main, parse_log, table

LOG = """Building DAG of jobs...
Using shell: /usr/bin/bash
[Fri Dec  4 01:13:00 2026]
localrule fit_rgb:
    input: results/tiny/subjects/a/landmarks.npz
    jobid: 7
    reason: Missing output files
[Fri Dec  4 01:13:05 2026]
rule pretrain_alpha:
    output: results/tiny/pretrain/alpha1/model.pt
    jobid: 3
    wildcards: strategy=alpha1
[Fri Dec  4 01:20:00 2026]
Finished jobid: 7 (Rule: fit_rgb)
1 of 4 steps (25%) done
[Fri Dec  4 01:20:00 2026]
localrule fit_rgb:
    jobid: 8
[Fri Dec  4 01:23:00 2026]
Finished jobid: 8 (Rule: fit_rgb)
[Fri Dec  4 01:37:05 2026]
Finished jobid: 3 (Rule: pretrain_alpha)
[Fri Dec  4 01:37:05 2026]
localrule evaluate_avatar:
    jobid: 11
"""


def test_job_times_per_rule_from_a_log(tmp_path):
    path = tmp_path / "run.snakemake.log"
    path.write_text(LOG)
    times = parse_log(path)
    assert set(times.rules) == {"fit_rgb", "pretrain_alpha"}
    assert times.rules["fit_rgb"].jobs == 2
    assert times.rules["fit_rgb"].seconds == 7 * 60 + 3 * 60
    assert times.rules["fit_rgb"].longest == 7 * 60
    assert times.rules["pretrain_alpha"].seconds == 24 * 60
    assert times.unfinished == {"evaluate_avatar": 1}  # started, never finished: not timed
    assert times.job_seconds == 34 * 60
    assert times.wall_seconds == 24 * 60 + 5
    text = table(times, cores=2)
    rows = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert rows[0].startswith("| pretrain_alpha | 1 | 24.0 | 71 % | 24.0 |")  # most job time first
    assert rows[1].startswith("| fit_rgb | 2 | 10.0 | 29 % | 7.0 |")
    assert "job time 34.0 min in 3 jobs; job time / 2 cores = 17.0 min" in text
    assert "unfinished (not timed): evaluate_avatar x1" in text


def test_a_file_without_jobs_is_a_one_line_error_naming_it(tmp_path, capsys):
    path = tmp_path / "notes.txt"
    path.write_text("hello\n")
    with pytest.raises(ConfigError, match="notes.txt: no finished Snakemake job"):
        parse_log(path)
    assert main([str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "notes.txt" in err
    assert main([str(tmp_path / "missing.log")]) == 1
    assert "missing.log: cannot read" in capsys.readouterr().err
