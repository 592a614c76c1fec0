import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse
import torch

from avatarlab.headmodel import HeadModel, HeadModelFileError, ProceduralSpec, load_head_model_data
from avatarlab.headmodel.procedural import build_procedural_head
from avatarlab.headmodel.sources import load_flame_pickle, load_landmark_embedding
from avatarlab.render import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer


@pytest.fixture(scope="module")
def small_head():
    return build_procedural_head(ProceduralSpec(n_shape=6, n_expression=4, n_texture=3))


class _FakeCh:
    """Pickles like chumpy.ch.Ch (its array under 'x' in the instance dict)."""

    def __init__(self, x):
        self.x = x


def write_flame_layout_pickle(path, data, protocol=2):
    module = types.ModuleType("chumpy.ch")
    _FakeCh.__module__, _FakeCh.__qualname__ = "chumpy.ch", "Ch"
    module.Ch = _FakeCh
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = types.ModuleType("chumpy"), module
    try:
        payload = {
            "f": data.faces.astype(np.uint32), "v_template": data.v_template.astype(np.float64),
            "shapedirs": _FakeCh(np.concatenate([data.shapedirs, data.exprdirs], -1).astype(np.float64)),
            "posedirs": data.posedirs.astype(np.float64),
            "J_regressor": scipy.sparse.csc_matrix(data.J_regressor.astype(np.float64)),
            "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
            "weights": data.lbs_weights.astype(np.float64), "bs_style": "lbs", "bs_type": "lrotmin",
        }
        path.write_bytes(pickle.dumps(payload, protocol=protocol))
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]


@pytest.mark.parametrize("protocol", [0, 2])
def test_flame_pickle_round_trip_without_chumpy(tmp_path, small_head, protocol):
    path = tmp_path / "generic_model.pkl"
    write_flame_layout_pickle(path, small_head, protocol)
    assert "chumpy" not in sys.modules
    arrays = load_flame_pickle(path, n_shape_total=small_head.shapedirs.shape[-1])
    np.testing.assert_allclose(arrays["v_template"], small_head.v_template)
    np.testing.assert_allclose(arrays["shapedirs"], small_head.shapedirs)
    np.testing.assert_allclose(arrays["exprdirs"], small_head.exprdirs)
    np.testing.assert_allclose(arrays["J_regressor"], small_head.J_regressor)
    assert arrays["parents"].tolist() == [-1, 0, 1, 1, 1]
    np.testing.assert_array_equal(arrays["faces"], small_head.faces)


def test_flame2020_source_runs_through_the_model(tmp_path, small_head):
    write_flame_layout_pickle(tmp_path / "generic_model.pkl", small_head)
    np.save(tmp_path / "landmark_embedding.npy", {"full_lmk_faces_idx": small_head.lmk_faces_idx[None],
                                                   "full_lmk_bary_coords": small_head.lmk_bary_coords[None],
                                                   "static_lmk_faces_idx": small_head.lmk_faces_idx[17:]},
            allow_pickle=True)
    # UV texture space in FLAME_texture.npz layout: left half of the map red, right half blue (0..255)
    tex = np.zeros((32, 32, 3), np.float32)
    tex[:, :16, 0], tex[:, 16:, 2] = 255, 255
    uv = (small_head.v_template[:, :2] - small_head.v_template[:, :2].min(0)) / np.ptp(small_head.v_template[:, :2], 0)
    np.savez(tmp_path / "FLAME_texture.npz", mean=tex, tex_dir=np.zeros((32, 32, 3, 2), np.float32), vt=uv,
             ft=small_head.faces)
    cfg = {"kind": "flame2020", "model_path": str(tmp_path / "generic_model.pkl"),
           "landmark_path": str(tmp_path / "landmark_embedding.npy"), "texture_path": str(tmp_path / "FLAME_texture.npz"),
           "n_shape": 300, "n_expression": 100, "n_texture": 50, "shape_components_in_file": 6}
    data = load_head_model_data(cfg)
    assert data.source.startswith("flame2020")
    model = HeadModel(data, n_shape=300, n_expression=100)
    assert model.n_shape == 6 and model.n_expression == 4 and model.n_texture == 2
    p = model.zeros(1)
    out = model(p["shape"], p["expression"], p["pose"])
    np.testing.assert_allclose(out.vertices[0].numpy(), small_head.v_template, atol=1e-6)
    render = HeadRenderer(model, background=(0, 1, 0))(p, orbit_camera(1.0, 0.0, 0.0, image_size=(64, 64)))
    row = render.rgb[0, :, 32]
    on_head = render.mask[0, 0, 32] > 0
    cols = torch.nonzero(on_head).squeeze(1)
    left, right = row[:, cols[: len(cols) // 3]], row[:, cols[-len(cols) // 3:]]
    assert left[0].mean() > 3 * left[2].mean() and right[2].mean() > 3 * right[0].mean()


def test_malicious_pickle_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

    path = tmp_path / "generic_model.pkl"
    path.write_bytes(pickle.dumps({"f": Evil()}, protocol=2))
    with pytest.raises(HeadModelFileError, match="generic_model.pkl.*refusing to load"):
        load_flame_pickle(path)
    assert not (tmp_path / "pwned").exists()


def test_bad_inputs_name_the_file_and_the_problem(tmp_path, small_head):
    with pytest.raises(HeadModelFileError, match="nothere.pkl: FLAME model file not found"):
        load_flame_pickle(tmp_path / "nothere.pkl")
    path = tmp_path / "partial.pkl"
    path.write_bytes(pickle.dumps({"f": small_head.faces, "v_template": small_head.v_template}, protocol=2))
    with pytest.raises(HeadModelFileError, match=r"partial.pkl: missing FLAME keys \['shapedirs'"):
        load_flame_pickle(path)
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(HeadModelFileError, match="plain.npy: expected a pickled dict"):
        load_landmark_embedding(tmp_path / "plain.npy")
    with pytest.raises(HeadModelFileError, match="model_path"):
        load_head_model_data({"kind": "flame2020", "model_path": None, "landmark_path": None})


def write_flame_layout_files(folder, head):
    """generic_model.pkl and landmark_embedding.npy of `head` in FLAME 2020's layout."""
    write_flame_layout_pickle(folder / "generic_model.pkl", head)
    np.save(folder / "landmark_embedding.npy", {"full_lmk_faces_idx": head.lmk_faces_idx[None],
                                                "full_lmk_bary_coords": head.lmk_bary_coords[None]},
            allow_pickle=True)


def _cylindrical_uv_texture(head, colour=(204, 153, 128), size=64):
    """A FLAME_texture.npz-layout texture space for `head`: a cylindrical unwrap (the face at u = 0.5), faces that
    cross the seam at the back of the head mapped to one extra texel corner, and one flat skin colour (0..255)."""
    x, y, z = head.v_template.T
    u = np.arctan2(x, z) / (2 * np.pi) + 0.5
    v = (y - y.min()) / np.ptp(y)
    vt = np.concatenate([np.stack([u, v], 1), [[0.0, 0.0]]]).astype(np.float32)
    ft = head.faces.copy()
    ft[np.ptp(u[head.faces], axis=1) > 0.5] = len(vt) - 1
    mean = np.broadcast_to(np.asarray(colour, np.float32), (size, size, 3)).copy()
    return {"mean": mean, "tex_dir": np.zeros((size, size, 3, 2), np.float32), "vt": vt, "ft": ft}


def test_alpha2_closes_flame2020s_open_mouth_with_new_faces_and_a_texture_edit(tmp_path, small_head):
    """seed 002, 3.4: FLAME has no mouth interior; for alpha2 new faces (no new vertices) close the mouth and the
    unwrap is painted for them. With the jaw open, alpha1's rays pass through the mouth into the head, alpha2's stop."""
    from avatarlab.headmodel import load_head_model
    from avatarlab.headmodel.mouth import MOUTH_COLOUR, boundary_loops

    write_flame_layout_files(tmp_path, small_head)
    np.savez(tmp_path / "FLAME_texture.npz", **_cylindrical_uv_texture(small_head))
    cfg = {"kind": "flame2020", "model_path": str(tmp_path / "generic_model.pkl"),
           "landmark_path": str(tmp_path / "landmark_embedding.npy"), "texture_path": str(tmp_path / "FLAME_texture.npz"),
           "n_shape": 6, "n_expression": 4, "n_texture": 2, "shape_components_in_file": 6}
    alpha1, alpha2 = load_head_model(cfg), load_head_model(cfg, mouth_interior=True)
    assert len(boundary_loops(alpha1.faces.numpy())) == 1 and boundary_loops(alpha2.faces.numpy()) == []
    assert alpha2.num_vertices == alpha1.num_vertices and alpha2.faces.shape[0] > alpha1.faces.shape[0]
    assert alpha2.source.endswith(":mouth") and not alpha1.source.endswith(":mouth")
    torch.testing.assert_close(alpha2.faces[: alpha1.faces.shape[0]], alpha1.faces)
    painted = (alpha2.albedo_model.mean - torch.tensor(MOUTH_COLOUR)).abs().sum(-1) < 1e-6
    assert 0 < int(painted.sum()) < 0.05 * painted.numel() and not bool(
        ((alpha1.albedo_model.mean - torch.tensor(MOUTH_COLOUR)).abs().sum(-1) < 1e-6).any())

    def render(model, jaw):
        p = model.zeros(1)
        p["pose"][0, 6] = jaw
        return HeadRenderer(model, background=(0, 1, 0))(p, orbit_camera(0.5, 0.0, 0.0, image_size=(128, 128)))

    for model in (alpha1, alpha2):  # the landmarks, on the unchanged vertices, are the same
        torch.testing.assert_close(render(model, 0.0).landmarks2d, render(alpha1, 0.0).landmarks2d)
    open1, open2 = render(alpha1, 0.35), render(alpha2, 0.35)
    cx, cy = open1.landmarks2d[0, 60:68].mean(0).round().long().tolist()
    mouth = (slice(cy - 1, cy + 2), slice(cx - 1, cx + 2))
    depth1, depth2 = float(open1.depth[0, 0][mouth].mean()), float(open2.depth[0, 0][mouth].mean())
    rgb1, rgb2 = open1.rgb[0, :, mouth[0], mouth[1]].mean((1, 2)), open2.rgb[0, :, mouth[0], mouth[1]].mean((1, 2))
    assert depth1 > depth2 + 0.05  # alpha1: the rays go through the open mouth to the inside of the head
    assert abs(depth2 - float(open2.depth[0, 0, cy - 4, cx])) < 0.02  # alpha2: they stop at the lips' new faces
    assert float(rgb2[0] / rgb2[1]) > 2.0 > float(rgb1[0] / rgb1[1])  # painted dark red, not the skin inside
    closed1, closed2 = render(alpha1, 0.0), render(alpha2, 0.0)
    assert float((closed1.rgb - closed2.rgb).abs().amax(1).gt(0.05).float().mean()) < 0.002  # jaw shut: no change


def test_closing_the_mouth_of_a_mesh_without_an_opening_says_so():
    from dataclasses import replace

    from avatarlab.headmodel.mouth import close_mouth

    open_mouth = build_procedural_head(ProceduralSpec(n_shape=6, n_expression=4, n_texture=3, mouth_interior=False))
    with pytest.raises(HeadModelFileError, match="no open mouth"):
        close_mouth(replace(close_mouth(open_mouth), source="closed.pkl"))


def test_a_flame2020_model_gets_the_head_and_face_regions_the_pipeline_needs(tmp_path, small_head):
    """FLAME's files name no regions; the portraits need `head` and the fits' truth errors `face`. Derived from the
    skinning and the landmarks, on a FLAME-layout copy of the procedural head they match the regions it builds."""
    write_flame_layout_files(tmp_path, small_head)
    data = load_head_model_data({"kind": "flame2020", "model_path": str(tmp_path / "generic_model.pkl"),
                                 "landmark_path": str(tmp_path / "landmark_embedding.npy"),
                                 "shape_components_in_file": 6})
    head, face = data.regions["head"], data.regions["face"]
    np.testing.assert_array_equal(head, small_head.regions["head"])
    # the procedural face reaches up the forehead, the derived one stops at the brows: most of it, little else
    theirs = small_head.regions["face"]
    assert (face & theirs).sum() > 0.8 * theirs.sum() and (face & theirs).sum() > 0.6 * (face | theirs).sum()
    assert not (data.regions["face"] & ~data.regions["head"]).any()


def test_flame2020_portraits_paint_the_hair_into_the_uv_texture(tmp_path):
    """The FFHQ stand-in with a UV-textured FLAME model: the scalp (placed from the template's landmarks, so the same
    vertices as the procedural head's on a FLAME-layout copy of it) is painted into the texels of the scalp faces."""
    from helpers import compose_config

    from avatarlab.headmodel import load_head_model
    from avatarlab.pretrain.portraits import hair_mask, hair_texels, render_portraits

    head = build_procedural_head(ProceduralSpec(n_shape=6, n_expression=4, n_texture=3))
    write_flame_layout_files(tmp_path, head)
    np.savez(tmp_path / "FLAME_texture.npz", **_cylindrical_uv_texture(head, size=256))
    files = [f"head_model.model_path={tmp_path / 'generic_model.pkl'}",
             f"head_model.landmark_path={tmp_path / 'landmark_embedding.npy'}",
             f"head_model.texture_path={tmp_path / 'FLAME_texture.npz'}", "head_model.shape_components_in_file=6",
             "head_model.n_shape=6", "head_model.n_expression=4", "head_model.n_texture=2"]
    cfg = compose_config(["scale=smoke", "head_model=flame2020", *files, "subject.portraits=2", "subject.video_size=64"])
    flame = load_head_model(cfg.head_model)
    procedural = HeadModel(head)
    hair = hair_mask(flame)
    assert torch.equal(hair, hair_mask(procedural)) and 0.1 < float(hair.float().mean()) < 0.6
    texels = hair_texels(flame, hair)
    assert texels.shape == (256, 256) and 0 < int(texels.sum()) < texels.numel()
    uv, uv_faces = flame.albedo_model.uv.numpy(), flame.albedo_model.uv_faces.numpy()
    faces = flame.faces.numpy()

    def texel(face):  # the texel under a face's UV centroid
        u, v = uv[uv_faces[face]].mean(0)
        return min(int((1 - v) * 256), 255), min(int(u * 256), 255)

    scalp = np.flatnonzero(hair.numpy()[faces].all(1))
    face = np.flatnonzero(head.regions["face"][faces].all(1))  # the procedural head's own face region
    assert np.mean([texels[texel(f)] for f in scalp]) > 0.9 and np.mean([texels[texel(f)] for f in face]) < 0.01
    params, chunks, source = render_portraits(cfg)
    images = np.concatenate(list(chunks))
    assert images.shape == (2, 64, 64, 3) and source.startswith("flame2020") and params["shape"].shape == (2, 6)
