"""Training: pretraining of the parametric head model and (later) per-subject fine-tuning."""
