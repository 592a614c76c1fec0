"""The names of the results tree's avatar folders, both ways: one key (subject, recipe, initialisation, frames
variant, seed) <-> one folder, `<results>/avatars/<subject>/<recipe>/<folder>` with

    <folder> = <init>[_frames<b|c>][_seed<k>]        (seed 0 and variant a leave their part out)

The workflow's rules, its Plan and the report's reader of finished runs all go through `AvatarKey`, so the
format is spelled here only.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

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
        return f"{results}/avatars/{self.subject}/{self.recipe}/{self.folder}"

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
