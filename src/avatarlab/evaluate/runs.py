"""The finished runs under a results tree, as the report and the claims read them: every folder with a train.json
and an eval.json, the avatars with their subject, recipe, initialisation, frame variant and seed, and the pooled
seed-to-seed noise of their test scores."""
from __future__ import annotations

from pathlib import Path

from avatarlab.evaluate.table import read_json
from avatarlab.seed_stats import pooled_sd
from avatarlab.workflow.layout import AvatarKey


def load_runs(results: Path, pattern: str) -> list[dict]:
    """Every folder matching `pattern` with a train.json and an eval.json: {dir, train, eval}."""
    runs = []
    for folder in sorted(p for p in results.glob(pattern) if p.is_dir()):
        train, ev = read_json(folder / "train.json"), read_json(folder / "eval.json")
        if train is not None and ev is not None:
            runs.append({"dir": folder, "name": folder.name, "train": train, "eval": ev})
    return runs


def load_avatars(results: Path) -> list[dict]:
    """avatars/<subject>/<recipe>/<folder>/ (the folder names the key: workflow/layout.py)."""
    avatars = load_runs(results, "avatars/*/*/*")
    for a in avatars:
        key = AvatarKey.parse(a["dir"].parent.parent.name, a["dir"].parent.name, a["dir"].name)
        a.update(subject=key.subject, recipe=key.recipe, init=key.init, variant=key.variant, seed=key.seed, key=key)
    return avatars


def seeded_runs(avatars: list[dict], subject: str, recipe: str, init: str) -> list[dict]:
    """The seeds of one avatar (all frames, variant a), by seed."""
    return sorted((a for a in avatars if (a["subject"], a["recipe"], a["init"], a["variant"]) ==
                   (subject, recipe, init, "a")), key=lambda a: a["seed"])


def seed_noise(avatars: list[dict], metric: str = "psnr") -> tuple[float | None, int]:
    """Pooled seed-to-seed standard deviation of an avatar's test `metric` over every seeded avatar."""
    groups: dict[tuple, list[float]] = {}
    for a in avatars:
        if a["variant"] == "a":
            groups.setdefault((a["subject"], a["recipe"], a["init"]), []).append(a["eval"]["all"]["model"][metric])
    return pooled_sd(groups.values())


def base_avatars(avatars: list[dict]) -> dict[tuple[str, str], dict]:
    """Seed 0's base-recipe avatars on all frames, by (subject, init)."""
    return {(a["subject"], a["init"]): a for a in avatars
            if a["recipe"] == "base" and a["variant"] == "a" and a["seed"] == 0}
