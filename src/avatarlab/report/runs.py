"""The finished runs under a results tree, as the report and the claims read them: every folder with a train.json
and an eval.json, the avatars with their subject, recipe, initialisation, frame variant and seed, and the pooled
seed-to-seed noise of their test scores."""
from __future__ import annotations

from avatarlab.metrics.seeds import pooled_sd
from avatarlab.workflow.layout import ResultsTree


def load_runs(tree: ResultsTree, stage: str, pattern: str) -> list[dict]:
    """Every folder of `stage` matching `pattern` with a train.json and an eval.json: {dir, name, train, eval}."""
    runs = []
    for folder in (p for p in tree.find(stage, pattern) if p.is_dir()):
        train, ev = tree.load(folder / "train.json"), tree.load(folder / "eval.json")
        if train is not None and ev is not None:
            runs.append({"dir": folder, "name": folder.name, "train": train, "eval": ev})
    return runs


def load_avatars(tree: ResultsTree) -> list[dict]:
    """The finished avatars, each with its key (subject, recipe, init, variant, seed: workflow/layout.py)."""
    avatars = load_runs(tree, "avatars", "*/*/*")
    for a in avatars:
        key = tree.key(a["dir"]).avatar
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
