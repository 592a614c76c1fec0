import numpy as np
import pytest
import torch

from avatarlab.headmodel import POSE_DIM, HeadModel, ProceduralSpec, clip_coefficients, load_procedural_head
from avatarlab.headmodel import procedural as P
from avatarlab.headmodel.flame import rodrigues


def neutral(model, batch=1):
    return model.zeros(batch)


def test_sizes_follow_flame_layout(head_data):
    v = head_data.v_template.shape[0]
    assert 3000 < v < 12000
    assert head_data.shapedirs.shape == (v, 3, 100)
    assert head_data.exprdirs.shape == (v, 3, 50)
    assert head_data.posedirs.shape == (v, 3, 36)  # 4 non-root joints x 9 rotation elements
    assert head_data.J_regressor.shape == (5, v)
    assert list(head_data.parents) == [-1, 0, 1, 1, 1]
    assert head_data.lmk_faces_idx.shape == (68,) and head_data.lmk_bary_coords.shape == (68, 3)
    np.testing.assert_allclose(head_data.lbs_weights.sum(1), 1.0, atol=1e-5)
    np.testing.assert_allclose(head_data.lmk_bary_coords.sum(1), 1.0, atol=1e-5)
    assert (head_data.lmk_bary_coords > -1e-4).all()


def test_lbs_identity_at_zero_pose(head_model, head_data):
    p = neutral(head_model)
    out = head_model(p["shape"], p["expression"], p["pose"])
    np.testing.assert_allclose(out.vertices[0].numpy(), head_data.v_template, atol=1e-6)
    # zero pose with shape/expression: the blendshapes alone, no skinning change
    torch.manual_seed(0)
    shape, expr = torch.randn(1, 100), torch.randn(1, 50)
    out = head_model(shape, expr, p["pose"])
    expected = head_data.v_template + np.einsum("vck,k->vc", head_data.shapedirs, shape[0].numpy()) + np.einsum(
        "vck,k->vc", head_data.exprdirs, expr[0].numpy())
    np.testing.assert_allclose(out.vertices[0].numpy(), expected, atol=1e-5)


def test_jaw_opening_moves_only_lower_face(head_model, head_data):
    p = neutral(head_model)
    rest = head_model(p["shape"], p["expression"], p["pose"]).vertices[0]
    p["pose"][0, 6] = 0.3  # jaw about x: opens the mouth
    opened = head_model(p["shape"], p["expression"], p["pose"]).vertices[0]
    moved = ((opened - rest).norm(dim=1) > 1e-5).numpy()
    y = head_data.v_template[:, 1]
    assert moved.sum() > 200
    assert (y[moved] < P.MOUTH_Y + 0.013).all(), "something above the mouth corners moved"
    assert not moved[head_data.regions["eyeball_left"] | head_data.regions["eyeball_right"]].any()
    # the lower lip goes down (the mouth opens) by several millimetres
    lower_lip = head_data.regions["lips"] & (y < P.MOUTH_Y)
    drop = (rest[lower_lip, 1] - opened[lower_lip, 1]).mean().item()
    assert drop > 0.005
    # the landmark gap between inner lips (62 upper, 66 lower) opens accordingly
    lm_rest = head_model(*[neutral(head_model)[k] for k in ("shape", "expression", "pose")]).landmarks3d[0]
    lm_open = head_model(p["shape"], p["expression"], p["pose"]).landmarks3d[0]
    assert (lm_open[62, 1] - lm_open[66, 1]) - (lm_rest[62, 1] - lm_rest[66, 1]) > 0.008


def test_eye_rotation_moves_only_its_eyeball(head_model, head_data):
    p = neutral(head_model)
    rest = head_model(p["shape"], p["expression"], p["pose"]).vertices[0]
    p["pose"][0, 9:12] = torch.tensor([0.0, 0.4, 0.0])  # left eye
    turned = head_model(p["shape"], p["expression"], p["pose"]).vertices[0]
    moved = ((turned - rest).norm(dim=1) > 1e-6).numpy()
    np.testing.assert_array_equal(moved, head_data.regions["eyeball_left"] & moved)
    assert moved.sum() > 0.9 * head_data.regions["eyeball_left"].sum() - 2  # all but the rotation-axis poles
    centre = rest[head_data.regions["eyeball_left"]].mean(0)
    np.testing.assert_allclose(turned[head_data.regions["eyeball_left"]].mean(0), centre, atol=1e-4)


def test_neck_rotation_is_rigid_for_the_head(head_model, head_data):
    p = neutral(head_model)
    rest = head_model(p["shape"], p["expression"], p["pose"])
    p["pose"][0, 3:6] = torch.tensor([0.1, 0.5, 0.0])
    turned = head_model(p["shape"], p["expression"], p["pose"])
    upper = torch.from_numpy(head_data.v_template[:, 1] > -0.02)
    a, b = rest.vertices[0, upper][::37], turned.vertices[0, upper][::37]
    np.testing.assert_allclose(torch.cdist(a, a).numpy(), torch.cdist(b, b).numpy(), atol=2e-4)
    R = rodrigues(torch.tensor([0.1, 0.5, 0.0]))
    d_rest = rest.landmarks3d[0, 45] - rest.landmarks3d[0, 36]
    d_turn = turned.landmarks3d[0, 45] - turned.landmarks3d[0, 36]
    np.testing.assert_allclose(d_turn.numpy(), (R @ d_rest).numpy(), atol=1e-3)


def test_coefficients_in_range_give_plausible_heads(head_model, head_data):
    torch.manual_seed(1)
    batch = 16
    shape = torch.empty(batch, 100).uniform_(-2, 2)
    expr = torch.empty(batch, 50).uniform_(-2, 2)
    out = head_model(shape, expr, torch.zeros(batch, POSE_DIM))
    disp = (out.vertices - torch.from_numpy(head_data.v_template)).norm(dim=-1)
    assert disp.max() < 0.03, "a coefficient vector in [-2, 2] moved a vertex by more than 3 cm"
    assert disp.mean() > 5e-4, "the bases do nothing"
    faces = torch.from_numpy(head_data.faces)
    v0, v1, v2 = (out.vertices[:, faces[:, k]] for k in range(3))
    ref = torch.from_numpy(head_data.v_template)
    area_ref = torch.cross(ref[faces[:, 1]] - ref[faces[:, 0]], ref[faces[:, 2]] - ref[faces[:, 0]], dim=-1).norm(dim=-1)
    area = torch.cross(v1 - v0, v2 - v0, dim=-1).norm(dim=-1)
    assert (area > 0.1 * area_ref).float().mean() > 0.999, "triangles collapse"
    colours = head_model.albedo(torch.empty(batch, 50).uniform_(-2, 2))
    assert colours.min() >= 0 and colours.max() <= 1
    clipped = clip_coefficients(torch.tensor([-3.0, -2.0, 0.5, 2.0, 7.0]))
    assert clipped.tolist() == [-2.0, -2.0, 0.5, 2.0, 2.0]


@pytest.mark.parametrize("name", ["shapedirs", "exprdirs"])
def test_bases_are_orthogonal_with_decreasing_std(head_data, name):
    basis = getattr(head_data, name).reshape(-1, getattr(head_data, name).shape[-1]).astype(np.float64)
    gram = basis.T @ basis
    std = np.sqrt(np.diag(gram))
    off = gram / np.outer(std, std) - np.eye(len(std))
    assert np.abs(off).max() < 1e-4
    assert (np.diff(std) < 0).all()
    albedo = head_data.albedo.basis.reshape(-1, head_data.albedo.basis.shape[-1])
    assert (np.diff(np.linalg.norm(albedo, axis=0)) < 0).all()


def test_every_parameter_moves_something(head_model):
    base = neutral(head_model)
    ref = head_model(base["shape"], base["expression"], base["pose"]).vertices
    for name, count in (("shape", 100), ("expression", 50), ("pose", 15)):
        for k in range(count):
            if name == "pose" and k < 3:  # root: rigid, also checked to move
                pass
            p = neutral(head_model)
            p[name][0, k] = 1.0 if name != "pose" else 0.2
            v = head_model(p["shape"], p["expression"], p["pose"]).vertices
            assert (v - ref).abs().max() > 1e-5, f"{name}[{k}] has no effect"
    p = neutral(head_model)
    tex = head_model.albedo(p["texture"])
    for k in range(head_model.n_texture):
        p["texture"][0] = 0
        p["texture"][0, k] = 1.0
        assert (head_model.albedo(p["texture"]) - tex).abs().max() > 1e-3, f"texture[{k}] has no effect"


def test_landmark_embedding_lands_on_the_designed_points(head_model):
    p = neutral(head_model)
    lm = head_model(p["shape"], p["expression"], p["pose"]).landmarks3d[0].numpy()
    np.testing.assert_allclose(lm[:, :2], P.landmark_xy(), atol=2e-4)
    assert (lm[:, 2] > 0.02).all(), "landmarks must sit on the front of the head"
    assert lm[30, 2] == lm[:, 2].max(), "the nose tip is the most forward landmark"


def test_mouth_interior_variant_and_cache(tmp_path):
    spec = ProceduralSpec(n_shape=10, n_expression=10, n_texture=5, mouth_interior=True)
    first = load_procedural_head(spec, tmp_path)
    cached = load_procedural_head(spec, tmp_path)
    assert len(list(tmp_path.glob("procedural_*.npz"))) == 1
    np.testing.assert_array_equal(first.v_template, cached.v_template)
    np.testing.assert_array_equal(first.albedo.basis, cached.albedo.basis)
    assert cached.regions["mouth_interior"].sum() > 50
    model = HeadModel(cached)
    p = model.zeros(1)
    p["pose"][0, 6] = 0.3
    v_open = model(p["shape"], p["expression"], p["pose"]).vertices[0]
    bag = torch.from_numpy(cached.regions["mouth_interior"])
    rest = torch.from_numpy(cached.v_template)
    lower = bag & (rest[:, 1] < rest[bag, 1].mean() - 0.004)
    assert (rest[lower, 1] - v_open[lower, 1]).mean() > 0.002, "the lower mouth interior must follow the jaw"
    plain = load_procedural_head(ProceduralSpec(n_shape=10, n_expression=10, n_texture=5), tmp_path)
    assert plain.v_template.shape[0] < cached.v_template.shape[0]
    with pytest.raises(ValueError, match="unresolved interpolation"):  # a raw head_model group read without the root
        load_procedural_head(spec, "${paths.cache}/headmodel")


def test_generation_is_deterministic():
    spec = ProceduralSpec(n_shape=20, n_expression=20, n_texture=10, seed=3)
    a, b = P.build_procedural_head(spec), P.build_procedural_head(spec)
    np.testing.assert_array_equal(a.shapedirs, b.shapedirs)
    c = P.build_procedural_head(ProceduralSpec(n_shape=20, n_expression=20, n_texture=10, seed=4))
    assert not np.array_equal(a.shapedirs, c.shapedirs), "the seed must change the random components"
