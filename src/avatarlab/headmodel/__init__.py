"""FLAME-structured head model: the real FLAME 2020 files when given, else the procedural open default."""
from __future__ import annotations

import logging
from pathlib import Path

from avatarlab.headmodel.flame import COEFFICIENT_RANGE, POSE_DIM, POSE_JOINTS, HeadModel, HeadOutput, clip_coefficients  # noqa: F401
from avatarlab.headmodel.mouth import close_mouth
from avatarlab.headmodel.procedural import ProceduralSpec, load_procedural_head
from avatarlab.headmodel.sources import HeadModelData, HeadModelFileError, load_flame2020  # noqa: F401

log = logging.getLogger(__name__)


def load_head_model_data(cfg) -> HeadModelData:
    """cfg: the `head_model` config group (a mapping). Logs which model is in use."""
    kind = cfg["kind"]
    if kind == "procedural":
        spec = ProceduralSpec(n_shape=cfg["n_shape"], n_expression=cfg["n_expression"], n_texture=cfg["n_texture"],
                              mouth_interior=bool(cfg.get("mouth_interior", False)), seed=cfg.get("seed", 0))
        data = load_procedural_head(spec, cfg.get("cache_dir"))
        log.info("head model: procedural open default (%s, %d vertices) - not the licensed FLAME model",
                 data.source, data.v_template.shape[0])
        return data
    if kind == "flame2020":
        if not cfg.get("model_path") or not cfg.get("landmark_path"):
            raise HeadModelFileError("head_model=flame2020 needs head_model.model_path (generic_model.pkl) and "
                                     "head_model.landmark_path (landmark_embedding.npy)")
        data = load_flame2020(Path(cfg["model_path"]), Path(cfg["landmark_path"]), cfg.get("texture_path"),
                              int(cfg.get("shape_components_in_file", 300)))
        log.info("head model: FLAME 2020 from %s (%d vertices)", cfg["model_path"], data.v_template.shape[0])
        if cfg.get("mouth_interior", False):
            data = close_mouth(data)  # alpha2's mouth (seed 002, 3.4): new faces and a texture edit
        return data
    raise ValueError(f"head_model.kind must be 'procedural' or 'flame2020', got {kind!r}")


def load_head_model(cfg, mouth_interior: bool = False) -> HeadModel:
    """cfg: the `head_model` config group. `mouth_interior`: the variant with the mouth interior whatever cfg says
    (alpha2's synthetic samples and those of every model continued from it; seed 002, 3.4)."""
    if mouth_interior:
        cfg = {**cfg, "mouth_interior": True}
    data = load_head_model_data(cfg)
    return HeadModel(data, n_shape=cfg["n_shape"], n_expression=cfg["n_expression"], n_texture=cfg["n_texture"])
