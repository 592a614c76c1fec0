"""The workflow's machinery as plain Python: what each step reads, its settings, code digest and command line."""
import shlex
import textwrap

import pytest
import yaml
from helpers import REPO
from hydra import compose, initialize_config_dir

from avatarlab.runtime.config import CONF_DIR
from avatarlab.runtime.provenance import code_digest, imported_modules, source_digest
from avatarlab.workflow.steps import Steps, declared_reads, hydra_string, hydra_value
from avatarlab.workflow.targets import Plan

HOSTILE = ["I don't know", 'say "hi", now', "a;b|c $(touch PWNED) `touch PWNED`", "x'|touch PWNED|'.mp4",
           "${oops}", "back\\slash", "end\\", "/tmp/obama's clip, 2.mp4", "[a,b]", "a=b", "ünïcode"]


@pytest.fixture(scope="module")
def steps():
    return Steps(CONF_DIR, "smoke", "procedural", ["speech.lr=0.01", "scale.crop_size=96"])


@pytest.mark.parametrize("text", HOSTILE)
def test_values_reach_hydra_verbatim(text):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"speech.say={hydra_string(text)}"])
    assert cfg.speech.say == text


@pytest.mark.parametrize("text", HOSTILE)
def test_values_reach_the_shell_as_one_word(text, steps):
    args = steps.args("avatarlab.speech.animate", values={"speech.say": text, "apps.out": f"out/{text}.mp4"})
    words = shlex.split(args)
    assert f"speech.say={hydra_string(text)}" in words and f"apps.out={hydra_string(f'out/{text}.mp4')}" in words


def test_numbers_lists_and_none_keep_their_type():
    assert (hydra_value(3), hydra_value(0.5), hydra_value(True), hydra_value(None)) == ("3", "0.5", "true", "null")
    assert hydra_value(["a b", "c,d"]) == '["a b","c,d"]'


def test_every_entry_module_declares_what_it_reads():
    modules = ["avatarlab.pretrain.train", "avatarlab.avatar.finetune", "avatarlab.avatar.evaluate",
               "avatarlab.pretrain.evaluate", "avatarlab.preprocess.fit_rgb", "avatarlab.speech.train",
               "avatarlab.report.build", "avatarlab.avatar.novel_views"]
    for module in modules:
        reads = declared_reads(module)
        assert reads and "scale" not in reads, f"{module}: sizes reach code through its sections, not cfg.scale"
    assert declared_reads("avatarlab.pretrain.train") == ("seed", "amp", "head_model", "render", "model",
                                                         "synthetic", "strategy", "pretrain", "tracking")


def test_settings_are_the_resolved_sections_a_step_reads(steps):
    settings = yaml.safe_load(steps.settings("avatarlab.pretrain.train", "strategy=beta4"))
    assert set(settings) == set(declared_reads("avatarlab.pretrain.train"))
    assert settings["strategy"]["name"] == "beta4" and settings["model"]["image_size"] == 64  # resolved from scale
    assert settings != yaml.safe_load(steps.settings("avatarlab.pretrain.train", "strategy=beta5"))


def test_a_user_override_reaches_only_the_steps_that_read_it(steps):
    speech = steps.args("avatarlab.speech.train")
    assert "speech.lr=0.01" in shlex.split(speech)
    assert "speech.lr=0.01" not in shlex.split(steps.args("avatarlab.preprocess.fit_rgb"))
    assert "speech.lr=0.01" not in shlex.split(steps.args("avatarlab.pretrain.train", "strategy=alpha1"))
    # a scale key reaches a step when one of the sections it reads refers to it
    assert "scale.crop_size=96" in shlex.split(steps.args("avatarlab.preprocess.frames"))
    assert "scale.crop_size=96" not in shlex.split(steps.args("avatarlab.speech.train"))
    assert yaml.safe_load(steps.settings("avatarlab.preprocess.frames"))["preprocess"]["image_size"] == 96


def test_code_digest_ignores_docstrings_and_comments_but_not_code(tmp_path):
    pkg = tmp_path / "avatarlab"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "helper.py").write_text('"""Helper."""\n\ndef f(x):\n    """Doc."""\n    return x + 1  # one\n')
    (pkg / "step.py").write_text("from avatarlab.helper import f\n\nprint(f(1))\n")
    before = code_digest("avatarlab.step", src=tmp_path)
    assert imported_modules("avatarlab.step", src=tmp_path) == ["avatarlab", "avatarlab.helper", "avatarlab.step"]
    (pkg / "helper.py").write_text('"""Helper, reworded."""\n\n\ndef f(x):\n    """Other doc."""\n'
                                   '    # a comment\n    return x + 1  # two\n')
    assert code_digest("avatarlab.step", src=tmp_path) == before
    (pkg / "helper.py").write_text('"""Helper."""\n\ndef f(x):\n    return x + 2\n')
    assert code_digest("avatarlab.step", src=tmp_path) != before


def test_tracking_and_error_modules_are_not_part_of_a_steps_code(tmp_path):
    pkg = tmp_path / "avatarlab"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "runtime").mkdir()
    (pkg / "runtime" / "__init__.py").write_text("")
    (pkg / "runtime" / "tracking.py").write_text("def log(x):\n    return None\n")
    (pkg / "step.py").write_text("from avatarlab.runtime.tracking import log\n\nlog(1)\n")
    before = code_digest("avatarlab.step", src=tmp_path)
    (pkg / "runtime" / "tracking.py").write_text("def log(x):\n    print(x)\n")
    assert code_digest("avatarlab.step", src=tmp_path) == before
    (pkg / "step.py").write_text("from avatarlab.runtime.tracking import log\n\nlog(2)\n")
    assert code_digest("avatarlab.step", src=tmp_path) != before


def test_docstring_edits_in_infrastructure_change_no_digest():
    io = REPO / "src" / "avatarlab" / "runtime" / "io.py"
    text = io.read_text()
    edited = text.replace('"""Atomic file writes', '"""Atomic file writes (reworded)', 1)
    assert edited != text
    assert source_digest(io) == _digest_of(edited, io.name)


def _digest_of(text, name):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        path.write_text(text)
        return source_digest(path)


def test_plan_lists_the_dissertations_experiments():
    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    config.update(scale="smoke", subjects={k: v for k, v in config["subjects"].items() if not v.get("optional")})
    # the seeds: the scale's unless the workflow config names them
    scales = {name: Steps(CONF_DIR, name, "procedural", []).compose().scale for name in ("smoke", "tiny")}
    assert Plan(config, scale=scales["smoke"]).seeds == 2 and Plan(config, scale=scales["tiny"]).seeds == 3
    config["seeds"] = 3
    plan = Plan(config, scale=scales["smoke"])
    assert len(plan.pretrained) == 14 and plan.speech_models == ["lstm_noreg", "lstm_reg", "window"]
    outputs = plan.avatar_outputs()
    plain = [o for o in outputs if "/base/" in o and "_frames" not in o and "_seed" not in o]
    assert len(plain) == 14 + 1  # 14 initialisations of synth_talk + the interpolation base of synth_turns
    assert plan.seeds == 3
    for s in plan.subjects:  # the final recipe with seeds 0, 1, 2
        for name in ("beta6_from_alpha2", "beta6_from_alpha2_seed1", "beta6_from_alpha2_seed2"):
            assert f"results/smoke/avatars/{s}/final/{name}/eval.json" in outputs
    seeded = sorted(o.split("/base/")[1] for o in outputs if "/base/" in o and "_seed" in o)
    assert seeded == [f"{a}_seed{k}/eval.json" for a in ("alpha1", "alpha2") for k in (1, 2)]
    assert plan.subject_values("portraits")["fit_rgb.mode"] == "images"
    # the interpolator's motion videos: synthesized and their frames extracted, never a subject of any experiment
    assert sorted(plan.motion_videos) == ["motion_talk", "motion_talk2", "motion_turns", "motion_turns2"]
    assert plan.subject_inputs("motion_talk") == ["results/smoke/subjects/motion_talk/input/video.mp4"]
    assert not [o for o in outputs + plan.pretrain_outputs() + plan.preprocessing_outputs() if "motion_" in o]
    with pytest.raises(ValueError, match="interp_motion_videos': synth_talk is also a subject"):
        Plan({**config, "interp_motion_videos": {"synth_talk": {"source": "synthetic"}}})
    final = plan.final_outputs()  # what results are made from is requested too: a lost model is remade
    for made in ("pretrain/beta5_from_alpha2/model.pt", "avatars/synth_talk/final/beta6_from_alpha2_seed1/model.pt",
                 "subjects/synth_turns/fit_rgb.npz", "subjects/portraits/masks.npz", "speech/lstm_reg/model.pt",
                 "interp/model.pt", "subjects/motion_talk/frames.json"):
        assert f"results/smoke/{made}" in final, made
    assert len(final) == len(set(final))
    figures = [o for o in plan.pretrain_outputs() if "/controls/" in o]
    assert figures == [f"results/smoke/pretrain/controls/{f}.json" for f in config["control_figures"]]
    only_alpha1 = Plan({**config, "alphas": ["alpha1"]})  # figures naming a model this run does not train: left out
    assert sorted(only_alpha1.control_figures) == []
    assert sorted(Plan({**config, "betas": ["beta4"]}).control_figures) == ["a4_expression", "fig27_29_fitted",
                                                                              "fig30_jaw"]


def test_optional_subject_without_files_is_skipped_with_a_note(capsys):
    plan = Plan({"scale": "smoke", "subjects": {"gone": {"source": "video", "path": "/nonexistent/*.mp4",
                                                         "optional": True}},
                 "real_images": {"name": "portraits", "source": "portraits"}, "alphas": [], "betas": [],
                 "renderers": [], "final_recipe": "x"})
    assert "gone" not in plan.subjects and "optional subject 'gone' skipped" in capsys.readouterr().err


def test_the_plans_rule_values():
    """What helpers.smk hands the rules comes from the Plan: inputs, config choices, audio and sweep tags."""
    from avatarlab.workflow.layout import AvatarKey

    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    config.update(scale="smoke", subjects={k: v for k, v in config["subjects"].items() if not v.get("optional")})
    plan = Plan(config, sweep_dir=REPO / "conf" / "sweep")
    c, a2 = AvatarKey("synth_talk", "base", "alpha1", "c"), AvatarKey("synth_talk", "final", "alpha2", seed=2)
    assert plan.interpolated_input(c) == ["results/smoke/subjects/synth_talk/interpolated.npz"]
    assert plan.interpolated_input(a2) == []
    assert plan.finetune_choices(a2) == ("finetune=final", "seed=2") and plan.finetune_choices(c) == ("finetune=base",)
    assert plan.real_set()["fit"] == "results/smoke/subjects/portraits/fit_rgb.npz"
    assert plan.speech_audio() == {"speech.say": config["speech_text"]}
    assert Plan({**config, "speech_wav": "me.wav"}).speech_audio() == {"speech.wav": "me.wav"}
    assert "finetune_ema" in plan.sweep_names("finetune") and "finetune_ema" not in plan.sweep_names("pretrain")
    assert plan.sweep_avatar("finetune_ema") == AvatarKey("synth_turns", "final", "beta6_from_alpha2")
    point = plan.sweeps["finetune_ema"].points[0]
    tags = plan.sweep_tags("finetune_ema", point.name)
    assert tags["tracking.point"] == point.name and tags["tracking.point_overrides"] == " ".join(point.overrides)


def test_the_chain_every_model_waits_for_starts_first():
    """Snakemake's priorities follow the chain: the pretraining image set's preprocessing, alpha, beta, the other
    subjects' preprocessing, the final recipe's fine-tunes, the side chains (speech, interpolation), the base
    fine-tunes; figures and scores last (test_workflow's dry run checks that the jobs carry them)."""
    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    config.update(scale="smoke", subjects={k: v for k, v in config["subjects"].items() if not v.get("optional")})
    plan = Plan(config, sweep_dir=REPO / "conf" / "sweep")
    real = plan.real_images["name"]
    order = [plan.step_priority("init_tracking"), plan.step_priority("fit_rgb", real),
             plan.step_priority("pretrain_alpha"), plan.step_priority("pretrain_beta"),
             plan.step_priority("fit_rgb", "synth_talk"), plan.step_priority("finetune_avatar", recipe="final"),
             plan.step_priority("speech_real_eval"), plan.step_priority("finetune_avatar", recipe="base"),
             plan.step_priority("evaluate_avatar")]
    assert order == sorted(order, reverse=True) and len(set(order)) == len(order), order
    assert plan.step_priority("synthesize_portraits") == plan.step_priority("detect_landmarks", real) == order[1]
    # a synthetic subject's video is the first step of its preprocessing, not a gap filler
    assert plan.step_priority("synthesize_subject", "synth_talk") == plan.step_priority("fit_rgb", "synth_talk")
    # the whole speech chain and the interpolator's share one priority: a chain's last step waits for its first
    side = {plan.step_priority(step) for step in ("speech_corpus", "speech_train", "speech_real_eval",
                                                  "train_interpolator", "interpolate_frames")}
    assert side == {plan.step_priority("speech_real_eval")}, side


def test_common_smk_only_wires(tmp_path):
    text = (REPO / "workflow" / "rules" / "common.smk").read_text()
    assert "import re" not in text and "ast." not in text, "no source scanning in the Snakefile"
    assert len(text.splitlines()) < 80, textwrap.shorten(text, 200)


def test_paper_scale_continues_the_final_recipe_at_256_and_512():
    """Seed 002: the 14 models and the ablations at 128², the final recipe then at 256² and 512²; the applications
    use the highest resolution's avatar. Smoke and tiny have no tiers."""
    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    config.update(subjects={k: v for k, v in config["subjects"].items() if not v.get("optional")})
    steps = Steps(CONF_DIR, "paper", "procedural", [])
    plan = Plan({**config, "scale": "paper"}, scale=steps.compose().scale)
    assert [(t.name, t.size, t.parent, t.start) for t in plan.tiers] == [
        ("beta6_from_alpha2_256px", 256, "beta6_from_alpha2", 312500),
        ("beta6_from_alpha2_512px", 512, "beta6_from_alpha2_256px", 612500)]
    assert plan.tiers[1].overrides() == ("model.image_size=512", "model.feature_size=64",
                                         "pretrain.alpha_iterations=612500", "pretrain.beta_iterations=300000")
    assert len(plan.pretrained) == 14 and plan.initialisations[14:] == [t.name for t in plan.tiers]
    outputs = plan.avatar_outputs()
    for s in plan.subjects:
        assert f"results/paper/avatars/{s}/final/beta6_from_alpha2_512px/eval.json" in outputs
        assert plan.final_avatar(s) == f"results/paper/avatars/{s}/final/beta6_from_alpha2_512px/model.pt"
    assert not any("px" in o for o in outputs if "/base/" in o), "the ablations stay at 128²"
    assert "results/paper/pretrain/beta6_from_alpha2_512px/eval.json" in plan.pretrain_outputs()
    tiny = Plan({**config, "scale": "tiny"}, scale=Steps(CONF_DIR, "tiny", "procedural", []).compose().scale)
    assert tiny.tiers == [] and tiny.final_avatar("synth_talk").endswith("final/beta6_from_alpha2/model.pt")
