"""Speech-driven animation of the avatar (seeds 000 and 001): audio features, phoneme timings, visemes in the head
model's expression/jaw space, the two animation models, and audio -> avatar video."""
