# avatarlab workflow: preprocess -> pretrain -> finetune -> evaluate -> report.
# `snakemake --cores 2` runs the main job (tiny scale, embedded default data); `--config scale=smoke` for seconds.
import os
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


# beside this Snakefile, so `--directory elsewhere` (a scratch or cluster work dir) still finds it
configfile: str(Path(workflow.basedir) / "workflow" / "config.yaml")


# your own subjects, written into the work folder by `avatarlab add-subject` (not committed): merged into `subjects`
if (Path.cwd() / "avatarlab.subjects.yaml").is_file():

    configfile: str(Path.cwd() / "avatarlab.subjects.yaml")


report: "workflow/report/workflow.rst"


# MLflow: the SQLite store under results/ by default; a tracking server when MLFLOW_TRACKING_URI is set (e.g. the
# PostgreSQL-backed one of cluster/local_cluster.sh), which is then passed on to every job, on a cluster too.
if os.environ.get("MLFLOW_TRACKING_URI"):

    envvars:
        "MLFLOW_TRACKING_URI",


include: "workflow/rules/common.smk"
include: "workflow/rules/helpers.smk"
include: "workflow/rules/headmodel.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/pretrain.smk"
include: "workflow/rules/avatar.smk"
include: "workflow/rules/speech.smk"
include: "workflow/rules/sweeps.smk"
include: "workflow/rules/report.smk"


# On a cluster these run on the submitting machine: bookkeeping and aggregate targets, no computation.
localrules:
    all,
    init_tracking,
    pretrain_all,
    avatars_all,
    speech_all,


rule all:
    input:
        get_final_output(),
    default_target: True
