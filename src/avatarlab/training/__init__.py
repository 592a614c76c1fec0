"""The training loop pretraining and fine-tuning share, and its resumable checkpoints."""
