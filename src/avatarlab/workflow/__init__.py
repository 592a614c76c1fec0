"""The workflow's machinery as plain Python (unit-tested; workflow/rules/common.smk only calls it): what each step
reads and runs with (steps.py) and which results a run produces (targets.py)."""
