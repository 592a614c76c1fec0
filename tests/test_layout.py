"""The results tree's avatar folder names (workflow/layout.py): one key <-> one folder, both ways, for every avatar
the workflow plans; the rules, the Plan and the report's reader use it."""
from __future__ import annotations

import re

import pytest

from avatarlab.workflow.layout import AvatarKey, alternation, avatar_folder_pattern


@pytest.mark.parametrize("folder, key", [
    ("beta6_from_alpha2", ("beta6_from_alpha2", "a", 0)),
    ("beta6_from_alpha2_seed2", ("beta6_from_alpha2", "a", 2)),
    ("beta6_from_alpha2_framesb", ("beta6_from_alpha2", "b", 0)),
    ("beta6_from_alpha2_framesc_seed1", ("beta6_from_alpha2", "c", 1)),
    ("beta6_from_alpha2_256px", ("beta6_from_alpha2_256px", "a", 0)),
    ("alpha1_seed10", ("alpha1", "a", 10)),
])
def test_an_avatar_folder_name_is_its_key_both_ways(folder, key):
    parsed = AvatarKey.parse("obama", "final", folder)
    assert (parsed.init, parsed.variant, parsed.seed) == key and parsed.subject == "obama"
    assert parsed.folder == folder and parsed.path("results/tiny") == f"results/tiny/avatars/obama/final/{folder}"
    assert re.fullmatch(avatar_folder_pattern(["alpha1", "beta6_from_alpha2", "beta6_from_alpha2_256px"]), folder)


def test_keys_that_no_folder_could_name_are_refused():
    with pytest.raises(ValueError, match="frames variant 'd'"):
        AvatarKey("s", "base", "alpha1", "d")
    with pytest.raises(ValueError, match="seed -1"):
        AvatarKey("s", "base", "alpha1", seed=-1)
    with pytest.raises(ValueError, match="ends like a variant or seed suffix"):
        AvatarKey("s", "base", "alpha1_seed3")
    assert [k.folder for k in AvatarKey("s", "final", "alpha2").seeds(3)] == ["alpha2", "alpha2_seed1", "alpha2_seed2"]


def test_wildcard_constraints_match_exactly_their_names():
    pattern = avatar_folder_pattern(["alpha1", "beta1_from_alpha1"])
    assert not re.fullmatch(pattern, "alpha2") and not re.fullmatch(pattern, "alpha1_seed0")
    assert not re.fullmatch(pattern, "alpha1_framesa")
    assert re.fullmatch(alternation(["a.b"]), "a.b") and not re.fullmatch(alternation(["a.b"]), "axb")
    assert not re.fullmatch(alternation([]), "") and not re.fullmatch(alternation([]), "anything")


def test_the_plan_names_every_avatar_through_the_layout(tmp_path):
    """Every avatar the tiny plan asks for parses to a key whose folder is its own name; the values a fine-tuning
    gets name the same variant and folder."""
    import yaml
    from helpers import REPO

    from avatarlab.workflow.steps import Steps
    from avatarlab.workflow.targets import Plan

    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    scale = Steps(REPO / "conf", "tiny", "procedural", []).compose().scale
    plan = Plan({**config, "scale": "tiny"}, sweep_dir=REPO / "conf" / "sweep", scale=scale)
    avatars = [o for o in plan.avatar_outputs() if "/avatars/" in o]
    keys = []
    for output in avatars:
        subject, recipe, folder = output.split("/avatars/")[1].split("/")[:3]
        key = AvatarKey.parse(subject, recipe, folder)
        assert key.folder == folder
        keys.append(key)
    assert {k.variant for k in keys} == {"a", "b", "c"} and {k.seed for k in keys} == {0, 1, 2}
    c = next(k for k in keys if k.variant == "c")
    values = plan.finetune_values(c, f"{c.path(plan.results)}/model.pt")
    assert values["finetune.frames_variant"] == "c" and values["finetune.out_dir"] == c.path(plan.results)
