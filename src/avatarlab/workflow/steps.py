"""What a workflow step depends on and how it is called.

Every entry module declares the config sections it reads (`READS = (...)`, see avatarlab/runtime/entry.py). A rule gets three
params (workflow/rules/common.smk `step_params`):
- `settings`: those sections, resolved (YAML) - a function of the wildcards only, so that Snakemake records it and a
  change to any of them, and to nothing else, reruns the step (params computed from input or output paths count as
  "derived" and are not compared);
- `code`: the digest of the code the module runs (its syntax without docstrings and comments, provenance.py) - so an
  edit that changes what runs reruns the step and a docstring or comment edit does not;
- `args`: the step's Hydra overrides for its command line: the scale, the user's `hydra_overrides` that touch what
  it reads (an override of `speech.lr` reaches the speech steps only), and the rule's own values (paths, names),
  each value quoted for Hydra's grammar and the whole for the shell (shlex), so no file name or text can become a
  sweep, an interpolation or a command.
"""
from __future__ import annotations

import ast
import os
import re
import shlex
import sys
from functools import lru_cache
from pathlib import Path

from avatarlab.runtime.provenance import SRC, code_digest, module_path


def interpreter_first_on_path() -> None:
    """The steps run `python -m ...`: the interpreter running Snakemake goes first on the PATH they inherit, so
    `.venv/bin/snakemake` works from a shell without the venv activated (an environment a deployment method such as
    --use-conda activates still puts its own first)."""
    here = str(Path(sys.executable).parent)
    os.environ["PATH"] = os.pathsep.join([here, os.environ.get("PATH", "")])


SCALES = ("smoke", "tiny", "paper")
SCALE_FILE = ".avatarlab-scale"  # in the work folder: the scale `make main SCALE=...` chose last


def chosen_scale(given: str | None, workdir: Path | None = None, say=None) -> str:
    """The scale of this call: the one given (`--config scale=...`), else the one remembered in the work folder's
    .avatarlab-scale (written by `make main SCALE=...`), else tiny; said in one line (`say`, default stderr)."""
    remembered = Path(workdir or Path.cwd()) / SCALE_FILE
    if given:
        scale, source = str(given), "given"
    elif remembered.is_file() and remembered.read_text().strip():
        scale, source = remembered.read_text().strip(), f"remembered in {remembered.name}"
    else:
        scale, source = "tiny", "the default"
    if scale not in SCALES:
        raise ValueError(f"scale {scale!r} ({source}): expected one of {', '.join(SCALES)}")
    (say or (lambda text: print(text, file=sys.stderr)))(f"avatarlab: scale {scale} ({source})")
    return scale


def declared_reads(module: str, src: Path = SRC) -> tuple[str, ...]:
    """The `READS` tuple of an entry module, read from its source (the module is not imported)."""
    tree = ast.parse(module_path(module, src).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "READS" for t in node.targets):
            return tuple(ast.literal_eval(node.value))
    raise ValueError(f"{module}: no READS = (...) declaration (the config sections the step reads)")


def hydra_value(value) -> str:
    """A value in Hydra's override grammar: numbers, booleans and None as they are, lists element by element, every
    string quoted (`hydra_string`)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_value(v) for v in value) + "]"
    return hydra_string(value)


def hydra_string(value) -> str:
    """A string as a quoted string of Hydra's override grammar: commas, brackets, quotes, `=` and `${...}` stay
    literal (backslashes are doubled only where the grammar would read them as escapes)."""
    v = str(value)
    quote = "'" if '"' in v else '"'  # double quotes read better inside the shell's single quotes
    v = re.sub(r"(\\*)\$\{", lambda m: m.group(1) * 2 + "\\${", v)
    v = re.sub(r"(\\*)" + quote, lambda m: m.group(1) * 2 + "\\" + quote, v)
    v = re.sub(r"(\\+)$", lambda m: m.group(1) * 2, v)
    return f"{quote}{v}{quote}"


def override_key(override: str) -> str:
    """The dotted key (or group) an override sets: `+a.b=1` -> `a.b`, `head_model=flame2020` -> `head_model`."""
    return override.split("=", 1)[0].lstrip("+~").strip()


class Steps:
    """Composes the steps' configs (conf/ + the workflow's scale, head model and overrides), once per variant."""

    def __init__(self, conf_dir: Path, scale: str, head_model: str, overrides=()):
        self.conf_dir = Path(conf_dir)
        self.base = (f"scale={scale}", f"head_model={head_model}")
        self.overrides = tuple(overrides)
        for override in self.overrides:
            key = override_key(override)
            if key == "hydra" or key.startswith(("hydra.", "hydra/")):
                raise ValueError(f"workflow config 'hydra_overrides': {override!r} is refused: it sets Hydra's own "
                                 "settings (callbacks, launcher, run folder), which a step never takes from the "
                                 "workflow config")

    @lru_cache(maxsize=None)
    def compose(self, extra: tuple[str, ...] = ()):
        from hydra import compose, initialize_config_dir

        from avatarlab.runtime.schema import validate

        with initialize_config_dir(config_dir=str(self.conf_dir), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*self.base, *self.overrides, *extra])
        validate(cfg)  # a wrong type, a negative size or an unknown choice stops the planning, before any job
        return cfg

    def touches(self, override: str, reads: tuple[str, ...], extra: tuple[str, ...] = ()) -> bool:
        """Whether a user override can change what a step reads: its key is one of the step's sections (or
        inside one), or a read section refers to it (`${scale.crop_size}` in `preprocess`)."""
        from omegaconf import OmegaConf

        key = override_key(override)
        top = key.split(".")[0]
        if top in reads or top in ("paths",):
            return True
        cfg = self.compose(extra)
        text = OmegaConf.to_yaml({k: cfg[k] for k in reads if k in cfg}, resolve=False)
        return f"${{{key}" in text or (key == top and f"${{{top}." in text)

    @staticmethod
    @lru_cache(maxsize=None)
    def code(module: str) -> str:
        """The code digest of a module that is not a Hydra step (a plain script)."""
        return code_digest(module)

    def settings(self, module: str, *extra: str) -> str:
        """YAML of the resolved sections `module` reads, in the config variant `extra` (group choices such as
        `strategy=beta4`)."""
        return self._variant(module, tuple(extra))[0]

    def args(self, module: str, *extra: str, values: dict | None = None, run_dir: str | None = None) -> str:
        """The shell-quoted command-line overrides of `python -m <module>`: scale, head model (when read), the
        user overrides that touch what it reads, the variant `extra` and the rule's own `values` (key -> value,
        quoted for Hydra here; e.g. paths of its inputs and outputs)."""
        args = list(self._variant(module, tuple(extra))[1])
        args += [f"{k}={hydra_value(v)}" for k, v in sorted((values or {}).items())]
        if run_dir:
            args.append(f"hydra.run.dir={hydra_string(run_dir)}")
        return " ".join(shlex.quote(a) for a in args)

    @lru_cache(maxsize=None)
    def _variant(self, module: str, extra: tuple[str, ...]) -> tuple[str, tuple[str, ...]]:
        """What a module's step depends on for one config variant: its settings and its fixed overrides."""
        from omegaconf import OmegaConf

        from avatarlab.runtime.entry import step_settings

        reads = declared_reads(module)
        settings = OmegaConf.to_yaml(OmegaConf.create(step_settings(self.compose(extra), reads)))
        args = [self.base[0]] + ([self.base[1]] if "head_model" in reads else [])
        args += [o for o in self.overrides if self.touches(o, reads, extra)] + list(extra)
        return settings, tuple(args)
