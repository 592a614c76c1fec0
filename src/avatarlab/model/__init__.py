"""The parametric head model of seed 002 section 3.1: a FLAME-conditioned NeRF (CNeRF) + a 2D neural renderer."""
