"""Sweeps as workflow citizens: a YAML file in conf/sweep/ names the step it varies and, in Hydra's own override
grammar, the values to try (`finetune.lr: 1e-4,3e-4,1e-3`, `seed: range(3)`, `choice(...)`, `interval` is not a
sweep). The overrides are expanded by Hydra's parser and basic sweeper - the grammar and the cartesian product of
`python -m ... -m` - into points; the workflow runs each point as ordinary Snakemake jobs under
`results/<scale>/sweeps/<sweep>/<point>/` (cached, resumable, SLURM-able), an MLflow run tagged `sweep` and `point`.

    step: finetune | pretrain
    finetune: subject, init (the pretrained model fine-tuned), recipe (base | final)
    pretrain: strategy, parent (the alpha model a beta strategy continues; none for alpha1/alpha2)
    overrides: {key: sweep expression}
    metric: the number the table and figure report (default psnr for avatars, psnr_head for pretrained models)
    also: more of the evaluation's model metrics shown beside it, each as a mean and 95 % CI over seeds (e.g.
          [landmark_nme, ssim]: what a setting that wins on the metric may cost elsewhere)
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from avatarlab.runtime.errors import ConfigError

SWEEP_DIR = Path(__file__).resolve().parents[3] / "conf" / "sweep"
STEPS = {"finetune": ("subject", "init"), "pretrain": ("strategy",)}
SEED_KEY = "seed"


@dataclass(frozen=True)
class Point:
    name: str                     # folder name: key-value pairs, e.g. lr-0.0001_seed-0
    overrides: tuple[str, ...]    # single-valued Hydra overrides, e.g. ("finetune.lr=0.0001", "seed=0")
    values: dict = field(hash=False, compare=False, default_factory=dict)  # key -> value (Python)

    @property
    def seed(self) -> int:
        return int(self.values.get(SEED_KEY, 0))

    @property
    def setting(self) -> tuple:
        """The point without its seed: the seeds of one setting share it."""
        return tuple((k, _hashable(v)) for k, v in self.values.items() if k != SEED_KEY)


@dataclass(frozen=True)
class Sweep:
    name: str
    step: str
    points: tuple[Point, ...]
    keys: tuple[str, ...]
    metric: str
    also: tuple[str, ...] = ()
    subject: str | None = None
    init: str | None = None
    recipe: str = "base"
    strategy: str | None = None
    parent: str | None = None
    description: str = ""
    choose_on: str = "psnr"   # the validation score a fine-tuning sweep chooses its setting on (CHOOSE_ON)


def _hashable(v):
    return tuple(_hashable(x) for x in v) if isinstance(v, (list, tuple)) else v


def _slug(value) -> str:
    if isinstance(value, (list, tuple)):
        return "-".join(_slug(v) for v in value)
    text = re.sub(r"[^A-Za-z0-9.+-]+", "", str(value))
    return text or "x"


def expand(overrides: dict) -> list[Point]:
    """The points of a sweep: Hydra's override parser and its basic sweeper's cartesian product."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    lines = [f"{k}={v}" for k, v in overrides.items()]
    parser = OverridesParser.create()
    try:
        parsed = parser.parse_overrides(lines)
        combos = BasicSweeper.split_arguments(parsed, max_batch_size=None)[0]
    except HydraException as err:
        raise ConfigError(f"sweep overrides {lines}: {err}".replace("\n", " ")) from None
    points, seen = [], set()
    for combo in combos:
        values = {}
        for item in parser.parse_overrides(combo):
            values[item.key_or_group] = item.value()
        name = "_".join(f"{key.split('.')[-1]}-{_slug(v)}" for key, v in values.items())
        while name in seen:
            name += "x"
        seen.add(name)
        points.append(Point(name, tuple(combo), values))
    return points


#: what a fine-tuning sweep may choose on: the validation frames' PSNR (higher is better) or ST-LPIPS (lower)
CHOOSE_ON = ("psnr", "st_lpips")


def load_sweep(path: str | Path, seeds: int | None = None) -> Sweep:
    """A sweep file, checked: one line naming the file and the problem when something is wrong. `seeds` (workflow
    config `sweep_seeds`) replaces the seed axis of a sweep that has one by seeds 0..seeds-1."""
    path = Path(path)
    try:
        spec = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
    step = spec.get("step")
    if step not in STEPS:
        raise ConfigError(f"{path}: step must be one of {sorted(STEPS)}, not {step!r}")
    missing = [k for k in STEPS[step] if not spec.get(k)]
    if missing:
        raise ConfigError(f"{path}: a {step} sweep needs {', '.join(missing)}")
    overrides = spec.get("overrides")
    if not isinstance(overrides, dict) or not overrides:
        raise ConfigError(f"{path}: 'overrides' must map config keys to sweep expressions")
    if seeds is not None and SEED_KEY in overrides:
        overrides = {**overrides, SEED_KEY: f"range({int(seeds)})"}
    try:
        points = expand({k: v for k, v in overrides.items()})
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    metric = spec.get("metric") or ("psnr" if step == "finetune" else "psnr_head")
    also = spec.get("also") or []
    if not isinstance(also, list) or not all(isinstance(m, str) for m in also):
        raise ConfigError(f"{path}: 'also' must be a list of metric names, not {also!r}")
    choose_on = spec.get("choose_on", "psnr")
    if choose_on not in CHOOSE_ON:
        raise ConfigError(f"{path}: choose_on must be one of {', '.join(CHOOSE_ON)} (a validation score), "
                          f"not {choose_on!r}")
    return Sweep(name=path.stem, step=step, points=tuple(points), keys=tuple(overrides), metric=metric,
                 also=tuple(m for m in also if m != metric),
                 subject=spec.get("subject"), init=spec.get("init"), recipe=spec.get("recipe", "base"),
                 strategy=spec.get("strategy"), parent=spec.get("parent"), description=spec.get("description", ""),
                 choose_on=choose_on)


def load_sweeps(folder: str | Path = SWEEP_DIR, seeds: int | None = None) -> dict[str, Sweep]:
    return {p.stem: load_sweep(p, seeds) for p in sorted(Path(folder).glob("*.yaml"))}
