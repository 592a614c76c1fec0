"""Stage: a subject's avatar (seed 002, 4). Fine-tuning (finetune), its score on the test frames beside the trivial
baselines (evaluate), and the applications: novel views, reenactment, telepresence."""
