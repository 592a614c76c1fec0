"""Stage: pretraining the parametric head model (seed 002, 3.2-3.4). The FFHQ stand-in portraits (portraits), the
strategies alpha1/alpha2/beta1-6 (train), their held-out scores (evaluate), control figures (controls), the renderer
experiment, and the head model's own checks (head_model_demo, dlib_check)."""
