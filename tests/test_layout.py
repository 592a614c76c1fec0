"""The results tree (workflow/layout.py): a result's key <-> its path, both ways, for every stage and every avatar
the workflow plans; the only module that spells a results path (the rules, the Plan and the report use it)."""
from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest
from helpers import REPO

from avatarlab.workflow.layout import (
    STAGES,
    AvatarKey,
    ResultsTree,
    alternation,
    avatar_folder_pattern,
    read_planned,
    write_planned,
)


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

    from avatarlab.workflow.steps import Steps
    from avatarlab.workflow.targets import Plan

    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    scale = Steps(REPO / "conf", "tiny", "procedural", []).compose().scale
    plan = Plan({**config, "scale": "tiny"}, sweep_dir=REPO / "conf" / "sweep", scale=scale)
    keys = []
    for output in plan.avatar_outputs():
        found = plan.tree.key(output)
        if found.stage == "avatars":
            assert found.avatar.folder == found.keys["folder"] and found.rest == ("eval.json",)
            assert plan.tree.avatar_of(found.avatar, "eval.json") == output
            keys.append(found.avatar)
    assert {k.variant for k in keys} == {"a", "b", "c"} and {k.seed for k in keys} == {0, 1, 2}
    c = next(k for k in keys if k.variant == "c")
    values = plan.finetune_values(c, f"{c.path(plan.results)}/model.pt")
    assert values["finetune.frames_variant"] == "c" and values["finetune.out_dir"] == c.path(plan.results)


def test_every_stage_path_turns_back_into_its_stage_and_keys():
    tree = ResultsTree("results/tiny")
    cases = [
        (tree.subject("obama", "fit_rgb.npz"), "subjects", {"subject": "obama"}, ("fit_rgb.npz",)),
        (tree.headmodel("render_grid.png"), "headmodel", {}, ("render_grid.png",)),
        (tree.pretrain("beta6_from_alpha2", "eval.json"), "pretrain", {"model": "beta6_from_alpha2"}, ("eval.json",)),
        (tree.controls("fig30_jaw.json"), "pretrain", {"model": "controls"}, ("fig30_jaw.json",)),
        (tree.interp("model.pt"), "interp", {}, ("model.pt",)),
        (tree.avatar("obama", "final", "alpha1_seed2", "eval.json"), "avatars",
         {"subject": "obama", "recipe": "final", "folder": "alpha1_seed2"}, ("eval.json",)),
        (tree.app("obama", "reenact_synth_talk.mp4"), "apps", {"subject": "obama"}, ("reenact_synth_talk.mp4",)),
        (tree.speech("lstm_reg", "metrics.json"), "speech", {}, ("lstm_reg", "metrics.json")),
        (tree.sweep("finetune_ema", "ema_decay-0.99_seed-1", "eval.json"), "sweeps", {"sweep": "finetune_ema"},
         ("ema_decay-0.99_seed-1", "eval.json")),
        (tree.report("tables", "claims.md"), "report", {}, ("tables", "claims.md")),
    ]
    assert {c[1] for c in cases} == set(STAGES)
    for path, stage, keys, rest in cases:
        assert path.startswith("results/tiny/" + stage + "/"), path
        found = tree.key(path)
        assert (found.stage, found.keys, found.rest) == (stage, keys, rest), path
    assert tree.key(cases[5][0]).avatar == AvatarKey("obama", "final", "alpha1", seed=2)
    # the rules' form: wildcards pass through; under a Path root the paths are Paths
    assert tree.subject("{subject}", "masks.npz") == "results/tiny/subjects/{subject}/masks.npz"
    assert ResultsTree(Path("/r")).pretrain("alpha1", "model.pt") == Path("/r/pretrain/alpha1/model.pt")


def test_a_path_outside_the_tree_or_its_stages_is_refused():
    tree = ResultsTree("results/tiny")
    with pytest.raises(ValueError, match="not under the results tree results/tiny"):
        tree.key("results/smoke/subjects/obama/fit_rgb.npz")
    with pytest.raises(ValueError, match="not in a stage folder"):
        tree.key("results/tiny/stray/file.json")
    with pytest.raises(ValueError, match="needs 3 folder level"):
        tree.key("results/tiny/avatars/obama/final")


def test_with_a_plan_the_tree_shows_only_the_planned_results(tmp_path):
    root = tmp_path / "results" / "tiny"
    tree = ResultsTree(root)
    for folder in ("alpha1", "alpha2", "beta6_from_alpha2"):  # alpha2: a leftover of an older configuration
        Path(tree.avatar("obama", "base", folder)).mkdir(parents=True)
        Path(tree.avatar("obama", "base", folder, "eval.json")).write_text("{}")
    Path(tree.app("obama")).mkdir(parents=True)
    for name in ("novel_views.png", "reenact_synth_talk.png"):
        Path(tree.app("obama", name)).write_bytes(b"png")
    planned = tmp_path / "planned.json"
    write_planned(planned, [tree.avatar("obama", "base", f, "eval.json") for f in ("alpha1", "beta6_from_alpha2")]
                  + [tree.app("obama", "novel_views.png")], root)
    # relative to the tree, so that the tree may move
    assert json.loads(planned.read_text())[0] == "apps/obama/novel_views.png"
    seen = ResultsTree(root, read_planned(planned))
    assert [p.name for p in seen.find("avatars", "*/*/*")] == ["alpha1", "beta6_from_alpha2"]
    assert [p.name for p in tree.find("avatars", "*/*/*")] == ["alpha1", "alpha2", "beta6_from_alpha2"]
    # a file beside a planned one belongs to the same result (the reenactment strip beside the novel views)
    assert [p.name for p in seen.find("apps", "*/*.png")] == ["novel_views.png", "reenact_synth_talk.png"]
    assert seen.load(tree.avatar("obama", "base", "alpha2", "eval.json")) is None
    assert seen.load(tree.avatar("obama", "base", "alpha1", "eval.json")) == {}
    bad = tmp_path / "bad.json"
    bad.write_text('{"not": "a list"}')
    with pytest.raises(ValueError, match=f"{bad}: expected a JSON list"):
        read_planned(bad)
    assert read_planned(None) is None


# a results path: a stage folder name followed by "/" (or a pathlib join with it)
_STAGE_LITERAL = re.compile(r"(?<![\w.-])(?:results|logs)/|(?<![\w-])(?:%s)/" % "|".join(STAGES))


def is_results_path(text: str) -> bool:
    """A string spelling a path of the results tree; not a sentence naming a folder, a help text's placeholder
    (results/<scale>) nor a file of the workflow's own folder (a report caption, ../report/x.rst)."""
    text = text.strip()
    return bool(_STAGE_LITERAL.search(text)) and " " not in text and "<" not in text and not text.startswith("../")


def _code_strings(path: Path):
    """The string constants of a module's code (docstrings and comments left out), with their line."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            yield node.lineno, node.value
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and isinstance(node.right, ast.Constant) \
                and node.right.value in STAGES:
            yield node.lineno, f"{node.right.value}/"  # a pathlib join


def path_literals(repo: Path) -> list[str]:
    found = []
    for path in sorted((repo / "src" / "avatarlab").rglob("*.py")):
        if path.name == "layout.py" and path.parent.name == "workflow":
            continue
        for line, text in _code_strings(path):
            if is_results_path(text):
                found.append(f"{path.relative_to(repo)}:{line}: {text!r}")
    for path in sorted((repo / "workflow" / "rules").glob("*.smk")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if re.search(r"\{(RESULTS|LOGS)\}", code) or any(is_results_path(s) for s in re.findall(r'"([^"]*)"', code)):
                found.append(f"{path.relative_to(repo)}:{number}: {line.strip()}")
    return found


def test_only_the_layout_module_spells_a_results_path():
    assert path_literals(REPO) == []


def test_the_path_literal_check_can_fail(tmp_path):
    (tmp_path / "src" / "avatarlab").mkdir(parents=True)
    (tmp_path / "workflow" / "rules").mkdir(parents=True)
    (tmp_path / "src" / "avatarlab" / "bad.py").write_text(
        '"""results/<scale>/avatars/... in a docstring is fine."""\n'
        'A = f"{root}/avatars/{s}"\nB = root / "pretrain" / name\nC = "see the subjects/ folder"\n')
    (tmp_path / "workflow" / "rules" / "bad.smk").write_text(
        'rule x:\n    output: f"{RESULTS}/subjects/x.json"  # comment about results/\n'
        '    log: "logs/x.log"\n')
    found = path_literals(tmp_path)
    assert [f.split(":")[0] + ":" + f.split(":")[1] for f in found] == [
        "src/avatarlab/bad.py:2", "src/avatarlab/bad.py:3", "workflow/rules/bad.smk:2", "workflow/rules/bad.smk:3"]
