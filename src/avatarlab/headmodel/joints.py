"""The head model's pose joints and coefficient range: constants every part of the head model shares (a module of
their own, so the model, its file sources and its derived regions import them without importing each other)."""
from __future__ import annotations

#: Pose layout of FLAME: root (global), neck, jaw, left eye, right eye; 3 axis-angle values each.
POSE_JOINTS = ("root", "neck", "jaw", "eye_left", "eye_right")
POSE_DIM = 3 * len(POSE_JOINTS)
#: Shape, expression and texture coefficients are meaningful in this range (seed 002, section 2.2).
COEFFICIENT_RANGE = (-2.0, 2.0)
