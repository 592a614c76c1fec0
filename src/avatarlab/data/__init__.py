"""Data sources: synthetic subjects and (later) the synthetic generator, real datasets and schedules."""
