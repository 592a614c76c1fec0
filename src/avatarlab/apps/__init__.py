"""Applications of a finished avatar (seed 002, 4.4): novel views, expression/pose transfer, telepresence."""
