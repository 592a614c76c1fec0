import itertools

import pytest
from helpers import compose_config
from omegaconf import OmegaConf

from avatarlab.cli import COMMANDS
from avatarlab.cli import main as cli_main
from avatarlab.headmodel import HeadModelFileError, load_head_model_data
from avatarlab.runtime.config import CONF_DIR

SCALES = sorted(p.stem for p in (CONF_DIR / "scale").glob("*.yaml"))
HEAD_MODELS = sorted(p.stem for p in (CONF_DIR / "head_model").glob("*.yaml"))


def test_groups_exist():
    assert SCALES == ["paper", "smoke", "tiny"]
    assert HEAD_MODELS == ["flame2020", "procedural"]


@pytest.mark.parametrize("scale,head_model", list(itertools.product(SCALES, HEAD_MODELS)))
def test_every_scale_and_head_model_composes(scale, head_model):
    cfg = compose_config([f"scale={scale}", f"head_model={head_model}"])
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved["scale"]["name"] == scale
    assert resolved["head_model"]["kind"] == head_model
    assert resolved["demo"]["out"].endswith(f"{scale}/headmodel/render_grid.png")
    assert resolved["demo"]["image_size"] == cfg.scale.demo_image_size


def test_mixed_precision_follows_the_scale_and_yields_to_an_override():
    """amp is a per-scale setting: float32 on the CPU scales (bfloat16 trained 1.47x slower on the Intel Xeon,
    README *Training speed*), float16 autocast at paper scale (GPU); `amp=...` on the command line still wins."""
    amp = {s: compose_config([f"scale={s}"]).amp for s in SCALES}
    assert amp == {"smoke": False, "tiny": False, "paper": True}
    assert compose_config(["scale=tiny", "amp=true"]).amp is True
    assert compose_config(["scale=paper", "scale.amp=false"]).amp is False


def test_scales_grow_and_nothing_is_hard_coded():
    sizes = {s: compose_config([f"scale={s}"]).scale for s in SCALES}
    assert sizes["smoke"].demo_image_size < sizes["tiny"].demo_image_size <= sizes["paper"].demo_image_size
    assert sizes["smoke"].dlib_check_renders < sizes["tiny"].dlib_check_renders < sizes["paper"].dlib_check_renders


def test_flame2020_without_files_fails_with_a_clear_message():
    cfg = compose_config(["head_model=flame2020"])
    with pytest.raises(HeadModelFileError, match="head_model.model_path"):
        load_head_model_data(cfg.head_model)
    cfg = compose_config(["head_model=flame2020", "head_model.model_path=/nonexistent/generic_model.pkl",
                          "head_model.landmark_path=/nonexistent/landmark_embedding.npy"])
    with pytest.raises(HeadModelFileError, match="/nonexistent/generic_model.pkl: FLAME model file not found"):
        load_head_model_data(cfg.head_model)


def test_cli_lists_commands(capsys):
    assert cli_main([]) == 2
    out = capsys.readouterr().out
    assert all(name in out for name in COMMANDS)
    assert {"run", "status", "add-subject", "report", "dashboard", "clean", "render-demo"} <= set(COMMANDS)


def test_status_names_the_changed_settings_instead_of_two_configs():
    """A dry run's "Params have changed" reason prints both resolved configs; `avatarlab status` reduces it to the
    keys that changed (and 'code' when the step's code digest did)."""
    from avatarlab.cli import changed_settings

    before = "seed: 0\nfit_rgb:\n  lr: 0.01\n  chunk: 16\n  held_out:\n    test_frames: 3\n"
    now = "seed: 0\nfit_rgb:\n  lr: 0.02\n  held_out:\n    test_frames: 3\n    test_clips: 1\n"
    block = ("fit_rgb:\n    input: a\n    reason: Params have changed since last execution: Union of exclusive params "
             f"before and now across all output: before: 'f27a0e66abee6610',{before!r} now: "
             f"'9fea103b66751803',{now!r} \n    wildcards: subject=s\n")
    assert changed_settings(block) == ["code", "fit_rgb.chunk (gone)", "fit_rgb.held_out.test_clips (new: 1)",
                                       "fit_rgb.lr: 0.01 -> 0.02"]
    same_code = block.replace("'f27a0e66abee6610',", "").replace("'9fea103b66751803',", "")
    assert changed_settings(same_code)[0] == "fit_rgb.chunk (gone)"
    assert changed_settings("x:\n    reason: Missing output files: a\n") == []


def test_each_scale_setting_is_written_once():
    """conf/scale/tiny.yaml holds every scale key (its value at tiny and its doc); smoke.yaml and paper.yaml inherit
    it (defaults: [tiny]) and write a key only where their value differs; a key no scale changes is no scale
    setting (its value belongs in its section of conf/), and every scale key is read somewhere in conf/."""
    import yaml

    conf = CONF_DIR
    repo = CONF_DIR.parent
    files = {name: yaml.safe_load((conf / "scale" / f"{name}.yaml").read_text()) for name in ("tiny", "smoke", "paper")}
    tiny = files["tiny"]
    for name in ("smoke", "paper"):
        assert files[name]["defaults"] == ["tiny", "_self_"], name
        repeated = [k for k, v in files[name].items() if k not in ("defaults", "name") and v == tiny.get(k)]
        assert not repeated, f"conf/scale/{name}.yaml repeats tiny's value of {repeated}"
        assert set(files[name]) - {"defaults"} <= set(tiny), f"{name}: keys tiny does not define"
    unchanged = [k for k in tiny if k != "name" and all(k not in files[n] for n in ("smoke", "paper"))]
    assert not unchanged, f"the same at every scale, so not scale settings: {unchanged}"
    text = "".join(p.read_text() for p in conf.rglob("*.yaml") if p.parent.name != "scale")
    code = "".join(p.read_text() for p in [*(repo / "src").rglob("*.py"), *(repo / "workflow").rglob("*.smk")]).lower()
    unread = [k for k in tiny if f"scale.{k}" not in text and f"scale.{k}" not in code and f'"{k}"' not in code
              and k != "name"]
    assert not unread, f"scale keys nothing reads: {unread}"
    for name in ("smoke", "tiny", "paper"):
        assert compose_config([f"scale={name}"]).scale.name == name
