"""What several tests share: config composition, fake preprocessed subjects, running the workflow."""
from helpers.config import compose_config, interp_config, step_cfg  # noqa: F401
from helpers.subjects import fake_real_set, fake_video_subject  # noqa: F401
from helpers.workflow import REPO, SHARED_DATA, run_snakemake, workflow_env  # noqa: F401
