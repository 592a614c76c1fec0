import numpy as np
import pytest
import torch

from avatarlab.render import orbit_camera, rasterize
from avatarlab.render.camera import Camera, intrinsics, scale_intrinsics
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.lighting import default_lighting


def inside_brute_force(tri, h, w):
    (x0, y0), (x1, y1), (x2, y2) = tri
    ys, xs = np.mgrid[0:h, 0:w] + 0.5

    def edge(ax, ay, bx, by):
        return (bx - ax) * (ys - ay) - (by - ay) * (xs - ax)

    e = np.stack([edge(x1, y1, x2, y2), edge(x2, y2, x0, y0), edge(x0, y0, x1, y1)])
    return (e >= 0).all(0) | (e <= 0).all(0)


def test_single_triangle_coverage_matches_brute_force():
    tri = [(2.2, 1.7), (13.1, 3.4), (4.6, 12.8)]
    screen = torch.tensor([[[x, y, 2.0] for x, y in tri]])
    frags = rasterize(screen, torch.tensor([[0, 1, 2]]), (16, 16))
    mask = frags.mask()[0, 0].numpy().astype(bool)
    np.testing.assert_array_equal(mask, inside_brute_force(tri, 16, 16))
    np.testing.assert_allclose(frags.bary.sum(-1).numpy(), 1.0, atol=1e-6)
    np.testing.assert_allclose(frags.depth.numpy(), 2.0, atol=1e-6)


@pytest.mark.parametrize("order", [[0, 1], [1, 0]])
def test_zbuffer_keeps_the_nearest_triangle(order):
    near = [[1.0, 1.0, 1.0], [15.0, 1.0, 1.0], [1.0, 15.0, 1.0]]
    far = [[0.0, 0.0, 3.0], [16.0, 0.0, 3.0], [0.0, 16.0, 3.0]]
    screen = torch.tensor([near + far])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])[order]
    frags = rasterize(screen, faces, (16, 16))
    depth = frags.to_image(frags.depth[:, None])[0, 0].numpy()
    near_mask = inside_brute_force([p[:2] for p in near], 16, 16)
    np.testing.assert_allclose(depth[near_mask], 1.0, atol=1e-6)
    assert (depth[~near_mask & (depth > 0)] == pytest.approx(3.0))


def test_a_batch_rasterizes_as_its_images_one_by_one():
    """The z-buffer pass over a whole batch (one slot per image and pixel) picks the same triangle per pixel as
    rasterizing each image alone, with overlapping triangles and a tiny chunk bound that splits the candidates."""
    import avatarlab.render.rasterizer as rasterizer

    g = torch.Generator().manual_seed(0)
    screen = torch.cat([torch.rand(3, 40, 2, generator=g) * 24 - 2, torch.rand(3, 40, 1, generator=g) + 0.5], -1)
    faces = torch.randint(0, 40, (30, 3), generator=g)
    whole = rasterize(screen, faces, (20, 20))
    chunked = rasterizer._PIXELS_PER_CHUNK
    try:
        rasterizer._PIXELS_PER_CHUNK = 50
        small_chunks = rasterize(screen, faces, (20, 20))
    finally:
        rasterizer._PIXELS_PER_CHUNK = chunked
    for frags in (whole, small_chunks):
        for b in range(3):
            alone = rasterize(screen[b:b + 1], faces, (20, 20))
            mine = frags.batch_idx == b
            assert mine.sum() == alone.face_idx.numel() > 20
            torch.testing.assert_close(frags.face_idx[mine], alone.face_idx, rtol=0, atol=0)
            torch.testing.assert_close(frags.pixel_y[mine] * 20 + frags.pixel_x[mine],
                                       alone.pixel_y * 20 + alone.pixel_x, rtol=0, atol=0)


def test_perspective_correct_depth_on_a_slanted_plane():
    K = intrinsics(40.0, (32, 32))
    cam = Camera(K=K, R=torch.eye(3)[None], t=torch.zeros(1, 3), image_size=(32, 32))
    verts = torch.tensor([[[-0.3, -0.3, 1.0], [0.3, -0.3, 2.0], [-0.3, 0.3, 1.0], [0.3, 0.3, 2.0]]])
    frags = rasterize(cam.project(verts), torch.tensor([[0, 1, 2], [1, 3, 2]]), (32, 32))
    # the plane is z = 1.5 + (x / 0.3) * 0.5, i.e. z = 1.5 + 5/3 x; a pixel ray is x = z (u - cx) / f
    u = frags.pixel_x.float() + 0.5
    slope = (u - 16.0) / 40.0
    z_true = 1.5 / (1 - (5.0 / 3.0) * slope)
    np.testing.assert_allclose(frags.depth.numpy(), z_true.numpy(), rtol=1e-4)


def test_barycentric_interpolation_gradcheck():
    screen = torch.tensor([[[1.3, 1.1, 1.0], [7.6, 2.2, 1.5], [2.4, 7.3, 2.0]]], dtype=torch.float64,
                          requires_grad=True)
    colours = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]]], dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2]])

    def image(s, c):
        frags = rasterize(s, faces, (8, 8))
        return frags.to_image(frags.interpolate(c, faces))

    assert torch.autograd.gradcheck(image, (screen, colours), eps=1e-6, atol=1e-5)


def test_camera_projection_and_scaled_intrinsics():
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(256, 256))
    centre = cam.project(torch.zeros(1, 1, 3))[0, 0]
    np.testing.assert_allclose(centre.numpy(), [128.0, 128.0, 1.0], atol=1e-5)
    point = torch.tensor([[[0.05, 0.08, 0.02]]])  # up and to the subject's left
    uvz = cam.project(point)[0, 0]
    assert uvz[0] > 128 and uvz[1] < 128 and uvz[2] < 1.0
    small = cam.scaled((32, 32))
    np.testing.assert_allclose(small.project(point)[0, 0, :2].numpy(), (uvz[:2] * 32 / 256).numpy(), rtol=1e-5)
    K = scale_intrinsics(cam.K, 0.5, 0.25)
    assert K[0, 0, 0] == pytest.approx(cam.K[0, 0, 0] * 0.5) and K[0, 1, 2] == pytest.approx(cam.K[0, 1, 2] * 0.25)
    side = orbit_camera(1.0, 90.0, 0.0, image_size=(256, 256))
    # seen from the subject's left (+x), the nose (+z) points to the left of the image, and +x is nearest
    assert side.project(torch.tensor([[[0.0, 0.0, 0.1]]]))[0, 0, 0] < 116
    assert side.project(torch.tensor([[[0.1, 0.0, 0.0]]]))[0, 0, 2] == pytest.approx(0.9)


@pytest.fixture(scope="module")
def frontal(head_model):
    renderer = HeadRenderer(head_model)
    params = head_model.zeros(2)
    params["pose"][1, 6] = 0.3
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(128, 128), batch=2)
    return renderer(params, cam), cam


def test_render_outputs_are_consistent(frontal):
    out, _ = frontal
    assert out.rgb.shape == (2, 3, 128, 128) and out.mask.shape == (2, 1, 128, 128)
    coverage = out.mask.mean().item()
    assert 0.2 < coverage < 0.6
    depth = out.depth[out.mask > 0]
    assert depth.min() > 0.85 and depth.max() < 1.15
    lm = out.landmarks2d.floor().long().clamp(0, 127)
    near_head = torch.nn.functional.max_pool2d(out.mask, 3, 1, 1)  # contour points lie on the silhouette
    assert near_head[0, 0, lm[0, :, 1], lm[0, :, 0]].all(), "every landmark projects onto the head"
    assert out.mask[0, 0, lm[0, 17:, 1], lm[0, 17:, 0]].all(), "inner landmarks lie inside the head mask"
    # skin-coloured face: more red than blue on the visible head
    rgb = out.rgb[0].permute(1, 2, 0)[out.mask[0, 0] > 0]
    assert (rgb[:, 0] > rgb[:, 2]).float().mean() > 0.9
    # the open mouth is dark between the lips
    mouth = out.landmarks2d[1, [62, 66]].mean(0).round().long()
    assert out.rgb[1, :, mouth[1], mouth[0]].mean() < 0.25 < out.rgb[0, :, mouth[1], mouth[0]].mean()


def test_pose_is_recovered_by_gradient_descent(head_model):
    torch.manual_seed(0)
    renderer = HeadRenderer(head_model)
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(96, 96))
    target_params = head_model.zeros(1)
    target_params["pose"][0, 3:6] = torch.tensor([0.1, 0.25, 0.0])
    target_params["pose"][0, 6] = 0.15
    with torch.no_grad():
        target_out = renderer(target_params, cam)
        target, target_lm = target_out.rgb, target_out.landmarks2d
    pose = torch.zeros(1, 6, requires_grad=True)
    optim = torch.optim.Adam([pose], lr=0.02)
    params = head_model.zeros(1)
    for _ in range(80):
        optim.zero_grad()
        p = dict(params, pose=torch.cat([params["pose"][:, :3], pose, params["pose"][:, 9:]], 1))
        geo = head_model(p["shape"], p["expression"], p["pose"])
        out = renderer.mesh_renderer(geo.vertices, head_model.albedo(p["texture"]), cam,
                                     default_lighting(1), geo.landmarks3d)
        # photometric + landmark terms, as in eq. 1: occlusion edges (the lips) give no photometric gradient
        loss = (out.rgb - target).abs().mean() + (out.landmarks2d - target_lm).abs().mean() / 96
        loss.backward()
        optim.step()
    err = (pose.detach()[0] - torch.tensor([0.1, 0.25, 0.0, 0.15, 0.0, 0.0])).abs()
    assert err[:4].max() < 0.03, f"pose not recovered: {pose.detach()}"


def test_vertex_offsets_follow_a_target_render(head_model):
    """A global vertex offset (translation) is found from photometric error alone."""
    renderer = HeadRenderer(head_model)
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(64, 64))
    params = head_model.zeros(1)
    geo = head_model(params["shape"], params["expression"], params["pose"])
    albedo = head_model.albedo(params["texture"])
    true_offset = torch.tensor([[[0.012, -0.008, 0.0]]])
    with torch.no_grad():
        target = renderer.mesh_renderer(geo.vertices + true_offset, albedo, cam, default_lighting(1)).rgb
    offset = torch.zeros(1, 1, 3, requires_grad=True)
    optim = torch.optim.Adam([offset], lr=0.002)
    for _ in range(60):
        optim.zero_grad()
        out = renderer.mesh_renderer(geo.vertices + offset, albedo, cam, default_lighting(1))
        (out.rgb - target).abs().mean().backward()
        optim.step()
    np.testing.assert_allclose(offset.detach()[0, 0, :2].numpy(), true_offset[0, 0, :2].numpy(), atol=0.002)
