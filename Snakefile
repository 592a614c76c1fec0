# avatarlab workflow: preprocess -> pretrain -> finetune -> evaluate -> report.
# `snakemake --cores 2` runs the main job (tiny scale, embedded default data); `--config scale=smoke` for seconds.
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


# beside this Snakefile, so `--directory elsewhere` (a scratch or cluster work dir) still finds it
configfile: str(Path(workflow.basedir) / "workflow" / "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/headmodel.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/pretrain.smk"
include: "workflow/rules/avatar.smk"
include: "workflow/rules/speech.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        get_final_output(),
    default_target: True
