"""The layout of the results tree, both ways: the only module that spells a results path.

    results/<scale>/                 (logs/<scale>/ mirrors it: each step's log where its outputs go)
        subjects/<subject>/...       preprocessing of one subject (frames, landmarks, masks, fits, interpolation)
        headmodel/...                the head model's parameter-sweep grid and the dlib check
        pretrain/<model>/...         a pretrained head model (alpha1, beta6_from_alpha2, ..., renderer_<name>)
        pretrain/controls/...        the control figures of pretrained models
        interp/...                   the frame interpolator
        avatars/<subject>/<recipe>/<folder>/...   a fine-tuned avatar (`AvatarKey`)
        apps/<subject>/...           the applications of a subject's final avatar
        speech/...                   speech-driven animation
        sweeps/<sweep>/[<point>/]... a sweep's table and its points
        report/...                   the report, the renderer experiment, the results card

An avatar's folder name carries its key: `<init>[_frames<b|c>][_seed<k>]` (seed 0 and variant a leave their part
out). `ResultsTree` turns a stage and its keys into a path (wildcards such as "{subject}" pass through, for the
rules) and `ResultsTree.key` turns a path back into its stage and keys; the workflow's rules, its Plan and the
report all go through it.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path, PurePosixPath

from avatarlab.runtime.io import atomic_path

VARIANTS = ("a", "b", "c")  # a: all training frames; b: every second dropped; c: b + the interpolated frames
_FOLDER = re.compile(r"^(?P<init>.+?)(?:_frames(?P<variant>[bc]))?(?:_seed(?P<seed>[1-9][0-9]*))?$")


@dataclass(frozen=True)
class AvatarKey:
    subject: str
    recipe: str  # base | final
    init: str  # the pretrained model it starts from (a tier's name included)
    variant: str = "a"
    seed: int = 0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"avatar frames variant {self.variant!r}: expected one of {', '.join(VARIANTS)}")
        if self.seed < 0:
            raise ValueError(f"avatar seed {self.seed}: expected >= 0")
        if _FOLDER.match(self.init).group("init") != self.init:
            raise ValueError(f"avatar initialisation {self.init!r} ends like a variant or seed suffix")

    @property
    def folder(self) -> str:
        """The avatar's folder name under avatars/<subject>/<recipe>/."""
        return (self.init + ("" if self.variant == "a" else f"_frames{self.variant}")
                + (f"_seed{self.seed}" if self.seed else ""))

    def path(self, results: str) -> str:
        return ResultsTree(results).avatar(self.subject, self.recipe, self.folder)

    @classmethod
    def parse(cls, subject: str, recipe: str, folder: str) -> AvatarKey:
        """The key of avatars/<subject>/<recipe>/<folder>."""
        match = _FOLDER.match(folder)
        if match is None:
            raise ValueError(f"avatars/{subject}/{recipe}/{folder}: not an avatar folder name")
        return cls(subject, recipe, match.group("init"), match.group("variant") or "a", int(match.group("seed") or 0))

    def seeds(self, count: int) -> list[AvatarKey]:
        """This avatar's seeded repeats 0..count-1 (seed 0 is the plain folder)."""
        return [AvatarKey(self.subject, self.recipe, self.init, self.variant, k) for k in range(count)]


def alternation(names) -> str:
    """A wildcard constraint matching exactly one of `names`; none: a pattern that matches nothing (an empty
    alternation would match '')."""
    return "|".join(re.escape(str(n)) for n in names) or "(?!)"


def avatar_folder_pattern(inits: list[str]) -> str:
    """A wildcard constraint for an avatar folder whose initialisation is one of `inits`."""
    return f"(?:{alternation(inits)})(?:_frames[bc])?(?:_seed[1-9][0-9]*)?"


#: the tracking store's readiness mark and its log, shared by every scale (the store: results/mlflow.db)
TRACKING_READY, TRACKING_LOG = "results/mlflow.ready", "logs/init_tracking.log"


def results_root(scale: str) -> str:
    """results/<scale>: a scale's results tree (relative to the work directory)."""
    return f"results/{scale}"


def logs_root(scale: str) -> str:
    """logs/<scale>: each step's log, in a tree that mirrors the results tree."""
    return f"logs/{scale}"


#: the stage folders under results/<scale>/, in pipeline order, each with the keys its folder levels name (the
#: levels below them are file names or sub-folders)
_KEY_NAMES = {"subjects": ("subject",), "headmodel": (), "pretrain": ("model",), "interp": (),
              "avatars": ("subject", "recipe", "folder"), "apps": ("subject",), "speech": (), "sweeps": ("sweep",),
              "report": ()}
STAGES = tuple(_KEY_NAMES)


@dataclass(frozen=True)
class ResultKey:
    """Where a path lies in the results tree: its stage, the keys of its folder (e.g. subject) and the rest."""
    stage: str
    keys: dict = field(default_factory=dict)
    rest: tuple = ()

    @property
    def avatar(self) -> AvatarKey | None:
        if self.stage != "avatars":
            return None
        return AvatarKey.parse(self.keys["subject"], self.keys["recipe"], self.keys["folder"])


@dataclass(frozen=True)
class ResultsTree:
    """results/<scale> (or logs/<scale>): a path per stage and keys, as a str under a str root (the rules' form,
    wildcards such as "{subject}" kept) or a Path under a Path root. `planned`: the files a workflow run asked the
    report for (`read_planned`); `find` and `load` then see only results in a folder holding one of them, so a
    folder left over from an older configuration never reaches a table."""
    root: str | Path
    planned: frozenset | None = None

    def _at(self, stage: str, *parts):
        parts = [str(p) for p in parts if p not in ("", None)]
        if isinstance(self.root, Path):
            return self.root.joinpath(stage, *parts)
        return "/".join([str(self.root), stage, *parts])

    def subject(self, subject: str, *names):
        """subjects/<subject>/...: one subject's preprocessing."""
        return self._at("subjects", subject, *names)

    def headmodel(self, *names):
        return self._at("headmodel", *names)

    def pretrain(self, model: str, *names):
        """pretrain/<model>/...: a pretrained head model (or `controls`, the control figures)."""
        return self._at("pretrain", model, *names)

    def controls(self, *names):
        return self.pretrain("controls", *names)

    def interp(self, *names):
        return self._at("interp", *names)

    def avatar(self, subject: str, recipe: str, folder: str, *names):
        """avatars/<subject>/<recipe>/<folder>/...: a fine-tuned avatar (folder: `AvatarKey.folder` or a wildcard)."""
        return self._at("avatars", subject, recipe, folder, *names)

    def avatar_of(self, key: AvatarKey, *names):
        return self.avatar(key.subject, key.recipe, key.folder, *names)

    def app(self, subject: str, *names):
        """apps/<subject>/...: the applications of a subject's final avatar."""
        return self._at("apps", subject, *names)

    def speech(self, *names):
        return self._at("speech", *names)

    def sweep(self, sweep: str, *names):
        """sweeps/<sweep>/...: a sweep's table and figure, and its points' folders."""
        return self._at("sweeps", sweep, *names)

    def report(self, *names):
        return self._at("report", *names)

    # --- back: a path's stage and keys ----------------------------------------------------------------------------
    def key(self, path) -> ResultKey:
        """The stage and keys of a path under this tree; ValueError for a path outside it or in no stage."""
        root, here = PurePosixPath(str(self.root)), PurePosixPath(str(path))
        try:
            parts = here.relative_to(root).parts
        except ValueError:
            raise ValueError(f"{path}: not under the results tree {self.root}") from None
        if not parts or parts[0] not in STAGES:
            raise ValueError(f"{path}: not in a stage folder of {self.root} ({', '.join(STAGES)})")
        stage, names = parts[0], _KEY_NAMES[parts[0]]
        depth = len(names)
        if len(parts) < 1 + depth:
            raise ValueError(f"{path}: a {stage} path needs {depth} folder level(s) below {stage}/")
        keys = dict(zip(names, parts[1:1 + depth]))
        result = ResultKey(stage, keys, parts[1 + depth:])
        result.avatar  # a malformed avatar folder name fails here
        return result

    # --- the finished results the report reads --------------------------------------------------------------------
    def find(self, stage: str, pattern: str) -> list[Path]:
        """Sorted existing paths matching `pattern` below a stage folder (e.g. find("apps", "*/telepresence.json");
        stage "controls": pretrain/controls), the planned ones only when the tree has a plan."""
        base = Path(self.controls() if stage == "controls" else self._at(stage))
        return [p for p in sorted(base.glob(pattern)) if self.in_plan(p)]

    def in_plan(self, path) -> bool:
        """Whether the report may read `path`: always without a plan; with one, when the path is a planned file,
        lies in a planned file's folder, or is a folder holding a planned file's folder."""
        if self.planned is None:
            return True
        files, folders = self._plan_index
        here = os.path.abspath(path)
        return (here in files or here in folders or os.path.dirname(here) in folders
                or any(f.startswith(here + os.sep) for f in folders))

    def load(self, path):
        """The JSON at `path`, or None when it is absent or not in the plan."""
        path = Path(path)
        return json.loads(path.read_text()) if path.is_file() and self.in_plan(path) else None

    @cached_property
    def _plan_index(self) -> tuple[frozenset, frozenset]:
        files = frozenset(os.path.abspath(os.path.join(self.root, p)) for p in self.planned)
        return files, frozenset(os.path.dirname(f) for f in files)


def write_planned(path: str | Path, files, root: str | Path, log: str | Path | None = None) -> None:
    """The result files a report is to read, relative to the tree's `root` (so the tree may move), as a sorted JSON
    list, atomically: a killed write leaves no half list. `log`: a one-line account."""
    names = sorted({PurePosixPath(os.path.relpath(f, root)).as_posix() for f in files})
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(json.dumps(names, indent=0) + "\n")
    if log is not None:
        Path(log).write_text(f"{len(names)} planned result files -> {path}\n")


def read_planned(path: str | Path | None) -> frozenset | None:
    """The files a report was asked to read, relative to its tree's root (a JSON list written by the workflow's
    report_inputs rule), or None: every finished result in the tree."""
    if path in (None, ""):
        return None
    try:
        names = json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a readable JSON list of result files ({err})") from None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path}: expected a JSON list of result file paths")
    return frozenset(str(PurePosixPath(n)) for n in names)
