import json

import numpy as np
import pytest
import torch
from helpers import SHARED_DATA, compose_config, interp_config

from avatarlab.headmodel import HeadModel
from avatarlab.metrics.alignment import procrustes_error_mm
from avatarlab.preprocess.crop import crop_and_resize, crop_points, frame_crops
from avatarlab.preprocess.fit_rgb import FitWeights, RGBFitter, choose_keyframes, fit_clip_lighting, rgb_fit_loss
from avatarlab.preprocess.fit_rgbd import depth_to_points, lift_landmarks, rgbd_block_losses, robust_landmarks
from avatarlab.preprocess.frames import (
    InputError,
    choose_crops,
    clip_ranges,
    expand_inputs,
    input_kind,
    load_frames,
    read_video,
    share_frames,
)
from avatarlab.preprocess.interp.network import XVFILite, backward_warp
from avatarlab.preprocess.masks import fill_missing, grabcut_mask, iou, temporal_vote
from avatarlab.render import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.mesh_renderer import vertex_normals


def test_bad_inputs_are_named(tmp_path):
    with pytest.raises(InputError, match="missing.mp4: input not found"):
        expand_inputs([tmp_path / "missing.mp4"])
    notes = tmp_path / "notes.txt"
    notes.write_text("hello")
    with pytest.raises(InputError, match="notes.txt: not a video"):
        input_kind(notes)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(InputError, match="broken.mp4: (OpenCV cannot open|no frames could be decoded)"):
        read_video(broken, None, None)


def test_crop_maps_points_consistently():
    frame = np.zeros((200, 300, 3), np.uint8)
    frame[120:123, 180:183] = 255  # a dot centred at pixel (181, 121): continuous centre (181.5, 121.5)
    meta = {"crop": {"cx": 170, "cy": 100, "side": 120}, "size": 60}
    out = crop_and_resize(frame, (170, 100, 120), 60)
    ys, xs = np.nonzero(out[..., 0] > 60)
    found = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    np.testing.assert_allclose(crop_points(np.array([[181.5, 121.5]]), meta)[0], found, atol=0.8)


def test_each_clip_has_its_crop_and_points_follow_their_frames_crop():
    assert clip_ranges(["a.mp4"] * 3 + ["b.mp4"] * 2 + ["a.mp4"]) == [(0, 3), (3, 5), (5, 6)]
    frame = np.zeros((200, 300, 3), np.uint8)
    frame[120:123, 180:183] = 255  # the dot of the test above, in two frames of two clips with other crops
    crops = [{"source": "a", "first": 0, "count": 1, "cx": 170, "cy": 100, "side": 120},
             {"source": "b", "first": 1, "count": 1, "cx": 190, "cy": 130, "side": 80}]
    meta = {"crops": crops, "count": 2, "size": 60}
    assert frame_crops(meta) == [(170, 100, 120), (190, 130, 80)]
    mapped = crop_points(np.array([[[181.5, 121.5]], [[181.5, 121.5]]]), meta)
    for i, crop in enumerate(frame_crops(meta)):
        ys, xs = np.nonzero(crop_and_resize(frame, crop, 60)[..., 0] > 60)
        np.testing.assert_allclose(mapped[i, 0], [xs.mean() + 0.5, ys.mean() + 0.5], atol=0.8)
    with pytest.raises(ValueError, match="do not cover every frame"):
        frame_crops({"crops": crops[:1], "count": 2})


def test_two_inputs_with_one_file_name_stay_two_clips(tmp_path):
    """`day1/clip` and `day2/clip`: two clips (two crops, two lightings, a clip to hold out), not one."""
    import cv2

    from avatarlab.data.subject_dir import SubjectDir

    inputs = []
    for day, value in (("day1", 40), ("day2", 200)):
        folder = tmp_path / day / "clip"
        folder.mkdir(parents=True)
        for i in range(2 if day == "day1" else 3):
            cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((24, 32, 3), value, np.uint8))
        inputs.append(folder)
    frames, sources, _, _ = load_frames(inputs + [inputs[0]], None, None)
    assert len(frames) == 7 and sources[:2] == ["clip", "clip"] and sources[2] == str(inputs[1])
    assert sources[5] == str(inputs[0]), "the same folder given twice is a third clip"
    assert clip_ranges(sources) == [(0, 2), (2, 5), (5, 7)]
    (tmp_path / "subject").mkdir()
    (tmp_path / "subject" / "frames.json").write_text(json.dumps({"count": 7, "sources": sources}))
    assert SubjectDir(tmp_path / "subject").frame_clips().tolist() == [0, 0, 1, 1, 1, 2, 2]


def test_a_frame_cap_keeps_every_clip(tmp_path):
    """`max_frames` caps a subject's frames in all, shared over its clips: eight clips capped at 12 frames are
    still eight clips (at smoke scale obama was one clip, and holding one out left nothing to train on)."""
    import cv2

    assert share_frames([30, 30, 30], None) == [30, 30, 30] and share_frames([5, 6], 20) == [5, 6]
    assert share_frames([20] * 8, 12) == [2, 2, 2, 2, 1, 1, 1, 1]
    assert share_frames([1, 40, 40], 21) == [1, 10, 10], "a short clip gives its share to the others"
    assert sum(share_frames([7, 3, 9, 2], 13)) == 13
    inputs = []
    for k, count in enumerate((6, 2, 6)):
        folder = tmp_path / f"clip{k}"
        folder.mkdir()
        for i in range(count):
            cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((16, 16, 3), 10 * i + 100 * k, np.uint8))
        inputs.append(folder)
    frames, sources, _, _ = load_frames(inputs, None, 8)
    assert sources == ["clip0"] * 3 + ["clip1"] * 2 + ["clip2"] * 3
    assert [int(f[0, 0, 0]) for f in frames] == [0, 20, 50, 100, 110, 200, 220, 250], \
        "each clip's share spread over the whole clip, its first and last frames included"



def test_a_capped_video_is_thinned_over_its_whole_length(tmp_path):
    """A video longer than its share of `max_frames` gives frames spread from its first to its last (a cut at the
    cap kept only its first seconds: at 15 fps obama's clips were their first 2 s), at the target frame rate's
    positions; a clip with no room left beside the others is left out with a warning, not an error."""
    import cv2

    from avatarlab.preprocess.frames import sampled_frames, spread

    assert spread(10, None).tolist() == list(range(10)) and spread(3, 5).tolist() == [0, 1, 2]
    assert spread(10, 4).tolist() == [0, 3, 6, 9] and spread(10, 0).tolist() == []
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 64))
    for i in range(30):
        writer.write(np.full((64, 64, 3), 8 * i, np.uint8))
    writer.release()
    assert sampled_frames(path, None) == 30 and sampled_frames(path, 5.0) == 6
    level = lambda frames: [int(round(float(f.mean()) / 8)) for f in frames]  # the frame's index
    frames, sources, fps, _ = load_frames([path], None, 4)
    assert level(frames) == [0, 10, 19, 29] and sources == ["clip.avi"] * 4 and abs(fps - 25) < 0.5
    frames, _, fps, _ = load_frames([path], 5.0, 3)  # every 5th frame: 0, 5, ..., 25; three of those six
    assert level(frames) == [0, 10, 25] and abs(fps - 5) < 0.5
    frames, _, _, _ = load_frames([path], 5.0, None)
    assert level(frames) == [0, 5, 10, 15, 20, 25]
    frames, sources, _, _ = load_frames([path, path, path], None, 2)
    assert len(frames) == 2 and sources == ["clip.avi", str(path)], "the third copy has no room: left out"

def test_real_clips_filmed_at_other_distances_come_out_centred_and_the_same_size():
    """Two obama clips: the head sits 0.85 m from the camera in one, 1.13 m in the other. With one crop per clip
    every clip's face is centred in its frames and its eyes as far apart; one crop for both leaves them apart."""
    clips = [SHARED_DATA / "obama" / f"{name}.mp4" for name in ("wa_yemen_suspect", "wa_young_americans")]
    if not all(c.is_file() for c in clips):
        pytest.skip(f"{clips[0].parent} is absent")
    from omegaconf import OmegaConf

    from avatarlab.preprocess.landmarks import detect_landmarks

    frames, sources = [], []
    for clip in clips:
        got, _ = read_video(clip, 2, 4)
        frames += got
        sources += [clip.name] * len(got)
    pre = OmegaConf.create({"crop_margin": 1.9, "crop_samples": 4, "detector_upsample": 1, "crop_per_clip": True})

    def faces(crops):
        per_frame = frame_crops({"crops": crops, "count": len(frames)})
        found = [detect_landmarks(crop_and_resize(f, c, 128)) for f, c in zip(frames, per_frame)]
        assert all(d is not None for d in found)
        points = [d.landmarks for d in found]
        eyes = [np.linalg.norm(p[36] - p[45]) for p in points]
        return np.array([p.mean(0) for p in points]), np.array(eyes)

    centres, eyes = faces(choose_crops(frames, sources, pre, ["video"]))
    one_centres, one_eyes = faces(choose_crops(frames, sources, OmegaConf.merge(pre, {"crop_per_clip": False}),
                                               ["video"]))
    assert np.abs(centres[:, 0] - 64).max() < 8  # every face centred across (its eyes and nose near the middle)
    assert np.abs(one_centres[:, 0] - 64).max() > 10  # one crop for both: neither clip's face is centred
    first = np.array(sources) == clips[0].name
    per_clip = eyes[first].mean() / eyes[~first].mean()  # measured: 1.07 with a crop per clip, 1.26 with one
    one_crop = one_eyes[first].mean() / one_eyes[~first].mean()
    assert abs(per_clip - 1) < 0.12 < abs(one_crop - 1)


def test_mask_helpers():
    masks = np.zeros((5, 4, 4), np.uint8)
    masks[[0, 1, 3, 4], 1:3, 1:3] = 1  # frame 2 lost the mask
    voted = temporal_vote(masks, 3)
    assert voted[2, 1:3, 1:3].all() and voted.sum() == 5 * 4
    found = np.array([True, True, False, True, True])
    filled = fill_missing(masks.copy(), found)
    assert (filled[2] == masks[1]).all()
    assert iou(masks[0] > 0, masks[0] > 0) == 1.0


@pytest.fixture(scope="module")
def synthetic_frame(head_model: HeadModel):
    renderer = HeadRenderer(head_model, background=(0.35, 0.45, 0.55))
    params = head_model.zeros(1)
    params["pose"][0, 6] = 0.2
    with torch.no_grad():
        out = renderer(params, orbit_camera(1.0, 0.0, 0.0, image_size=(192, 192)))
    image = (out.rgb[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    return image, out


def test_grabcut_mask_follows_the_head(synthetic_frame):
    image, out = synthetic_frame
    mask = grabcut_mask(image, out.landmarks2d[0].numpy())
    assert iou(mask > 0, out.mask[0, 0].numpy() > 0) > 0.8


def test_keyframes_cover_the_yaw_range():
    yaw = np.array([0, 5, -40, 10, 60, -5, 20, 3])
    keys = choose_keyframes(yaw, 3)
    assert set(keys) >= {2, 4} and len(keys) == 3
    assert list(choose_keyframes(yaw, 10)) == list(range(8))


def test_rgb_fit_loss_is_zero_at_a_perfect_fit_and_names_each_term():
    img = torch.rand(2, 3, 8, 8)
    lmk = torch.rand(2, 68, 2) * 8
    zeros = lambda n: torch.zeros(1, n)  # noqa: E731
    terms = rgb_fit_loss(img, img, torch.ones(2, 1, 8, 8), lmk, lmk, torch.ones(2), zeros(5), torch.zeros(2, 4),
                         zeros(3), torch.zeros(2, 15), FitWeights(), 8)
    assert set(terms) == {"photometric", "landmarks", "shape_reg", "expression_reg", "texture_reg", "pose_reg",
                          "eye_symmetry", "total"}
    assert float(terms["total"]) == pytest.approx(0.0, abs=1e-6)
    pose = torch.zeros(2, 15)
    pose[:, 9:12] = 0.3  # only the left eye turned: the eye-symmetry term of eq. 1 sees it
    terms = rgb_fit_loss(img, img * 0.5, torch.ones(2, 1, 8, 8), lmk + 1, lmk, torch.ones(2), zeros(5) + 1,
                         torch.zeros(2, 4), zeros(3), pose, FitWeights(), 8)
    assert terms["eye_symmetry"] > 0 and terms["photometric"] > 0 and terms["landmarks"] > 0 and terms["shape_reg"] > 0


def test_procrustes_error_ignores_similarity_transforms():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    c, s = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert procrustes_error_mm(pts, 1.3 * pts @ R.T + 2.0) == pytest.approx(0.0, abs=1e-9)
    assert procrustes_error_mm(pts, pts + rng.normal(0, 0.001, pts.shape)) > 0.5


def test_each_clip_of_a_video_gets_its_own_lighting(head_model):
    """Two clips of one head under other light (the second warmer and darker, as another room or white balance):
    refitted per clip from the shared lighting, the first clip's lighting stays put and the second's renders its
    colour again."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle
    from omegaconf import OmegaConf

    from avatarlab.render.lighting import default_lighting

    size = 64
    camera = orbit_camera(0.6, image_size=(size, size), batch=4)
    fitter = RGBFitter(head_model, size, FitWeights(), 0.02, (0.35, 0.45, 0.55))
    shared_light = default_lighting(1)
    warm = shared_light.clone()
    warm[:, 0] *= torch.tensor([1.15, 0.9, 0.7])
    params = head_model.zeros(4)
    shared = {"shape": params["shape"][:1], "texture": params["texture"][:1], "lighting": shared_light,
              "focal": camera.K[:1, 0, 0].log()}
    result = {"expression": params["expression"], "pose": params["pose"],
              "rot": rotation_matrix_to_axis_angle(camera.R), "trans": camera.t}
    with torch.no_grad():
        renders = [fitter.render(**shared_of, **result)[0] for shared_of in
                   (shared, dict(shared, lighting=warm))]
    images = torch.cat([renders[0].rgb[:2], renders[1].rgb[2:]])
    masks = torch.cat([renders[0].mask[:2], renders[1].mask[2:]])
    landmarks = renders[0].landmarks2d
    clips, fitted = np.array([0, 0, 1, 1]), np.ones(4, bool)
    fit = OmegaConf.create({"lighting_frames": 1, "lighting_iterations": 150, "lighting_lr": 0.05})
    lighting, losses = fit_clip_lighting(fitter, shared, result, fitted, images, landmarks, masks, clips, fit)
    assert lighting.shape == (4, 9, 3) and len(losses) == 2
    np.testing.assert_allclose(lighting[:2, 0], shared_light[:, 0].expand(2, -1), rtol=0.03)
    with torch.no_grad():  # (the SH bands trade off on one side of a head: compared as images, not coefficients)
        refit = fitter.render(**dict(shared, lighting=lighting[2:]), **{k: v[2:] for k, v in result.items()})[0]
    error = ((refit.rgb - images[2:]).abs() * masks[2:]).sum() / masks[2:].sum()
    shared_error = ((renders[0].rgb[2:] - images[2:]).abs() * masks[2:]).sum() / masks[2:].sum()
    assert error < 0.2 * shared_error
    colour = (refit.rgb * masks[2:]).sum((0, 2, 3)) / masks[2:].sum()
    np.testing.assert_allclose(colour, (images[2:] * masks[2:]).sum((0, 2, 3)) / masks[2:].sum(), atol=0.01)


def test_rgbd_pieces_are_exact_on_synthetic_depth(head_model, synthetic_frame):
    _, out = synthetic_frame
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(192, 192))
    K = cam.K[0].numpy()
    depth, mask = out.depth[0, 0].numpy(), out.mask[0, 0].numpy()
    params = head_model.zeros(1)
    params["pose"][0, 6] = 0.2
    geo = head_model(params["shape"], params["expression"], params["pose"])
    true_lmk = cam.world_to_camera(geo.landmarks3d)[0].detach().numpy()
    lifted, valid = lift_landmarks(out.landmarks2d[0].numpy(), depth, K, window=0)
    inner = np.arange(17, 48)  # brows, nose, eyes: on smooth surface
    assert np.linalg.norm(lifted[inner] - true_lmk[inner], axis=1).mean() < 0.002
    outlier = lifted.copy()
    outlier[30, 2] += 0.1  # a landmark that sees through the mouth
    _, _, kept = robust_landmarks(head_model, outlier, valid & (np.arange(68) >= 17))
    assert not kept[30] and kept[36:48].all()
    cloud = torch.from_numpy(depth_to_points(depth, mask, K)).float()
    verts = cam.world_to_camera(geo.vertices)[0].detach()
    terms = rgbd_block_losses(torch.from_numpy(true_lmk), torch.from_numpy(true_lmk), verts,
                              vertex_normals(verts[None], head_model.faces)[0], cloud, (1.0, 1000.0))
    assert float(terms["block1"]) < 1e-6
    assert np.sqrt(float(terms["block3"])) < 0.0015, "at the true parameters the point-to-mesh error is sub-mm"


def test_backward_warp_shifts_and_interpolator_starts_as_cross_fade():
    img = torch.zeros(1, 1, 6, 6)
    img[..., 2, 3] = 1.0
    flow = torch.zeros(1, 2, 6, 6)
    flow[:, 0] = 1.0  # sample one pixel to the right
    assert backward_warp(img, flow)[0, 0, 2, 2] == pytest.approx(1.0)
    wide, shift = torch.rand(1, 3, 4, 128), torch.full((1, 2, 4, 128), 0.3)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # as the interpolator trains: positions stay float32
        low = backward_warp(wide, shift.bfloat16())
    assert low.dtype == torch.float32
    assert float((low - backward_warp(wide, shift)).abs().max()) < 2e-3, "no 1/2-pixel rounding of the positions"
    net = XVFILite(width=8, scales=2)
    a, b = torch.rand(2, 3, 16, 16), torch.rand(2, 3, 16, 16)
    np.testing.assert_allclose(net(a, b).detach().numpy(), (0.5 * (a + b)).numpy(), atol=1e-5)


def test_the_interpolator_started_from_farneback_flows_is_the_farneback_baseline_until_trained():
    """flow_init=farneback: untrained, the network is the classical baseline (to the baseline's 8-bit rounding); a
    moving disc is put half-way, where the cross-fade shows two faint discs."""
    from avatarlab.preprocess.interp.optical_flow import interpolate_farneback

    yy, xx = np.mgrid[:64, :64]

    def disc(cx):
        img = np.zeros((64, 64, 3), np.uint8)
        img[(yy - 32) ** 2 + (xx - cx) ** 2 < 80] = [200, 120, 60]
        return img

    a, b, middle = disc(26), disc(34), disc(30)
    ta, tb, tm = (torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255 for x in (a, b, middle))
    baseline = torch.from_numpy(interpolate_farneback(a, b)).permute(2, 0, 1)[None].float() / 255
    for keep_unwarped in (False, True):  # the unwarped share starts at zero
        net = XVFILite(width=8, scales=3, flow_init="farneback", keep_unwarped=keep_unwarped)
        with torch.no_grad():
            out = net(ta, tb)
        assert float((out - baseline).abs().max()) < 1 / 255
        assert float((out - tm).abs().mean()) < 0.2 * float((0.5 * (ta + tb) - tm).abs().mean())
    with torch.no_grad():  # a full share (10 * 0.2 * sigmoid(0) = 1) is the cross-fade itself
        net.synthesis.keep.fill_(0.2)
        out = net(ta, tb)
    np.testing.assert_allclose(out.numpy(), (0.5 * (ta + tb)).numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="flow_init"):
        XVFILite(width=8, flow_init="raft")


def test_pixels_with_a_still_flow_are_not_warped_and_the_length_is_chosen_on_validation(monkeypatch):
    """still_flow_px: flow vectors shorter than it are set to zero (the frame's own pixel, no bilinear blur); the
    pretraining keeps the candidate its validation triplets score best."""
    from avatarlab.preprocess.interp import training

    flow = torch.zeros(1, 2, 2, 2)
    flow[0, 0, 0, 0], flow[0, 1, 0, 1], flow[0, 0, 1, 0] = 0.1, -0.3, 2.0
    kept = XVFILite(width=8, scales=2, still_flow_px=0.25).unwarp_still(flow)
    assert kept[0, :, 0, 0].tolist() == [0, 0] and kept[0, 1, 0, 1] == pytest.approx(-0.3) and kept[0, 0, 1, 0] == 2
    assert torch.equal(XVFILite(width=8, scales=2).unwarp_still(flow), flow)  # 0: every pixel warped
    # a disc moving 2 px: untrained and started from Farneback's flows, it is Farneback's frame; with a length above
    # every flow nothing is warped, and the untrained synthesis is the cross-fade
    yy, xx = np.mgrid[:32, :32]
    a, b = (torch.from_numpy(((yy - 16) ** 2 + (xx - cx) ** 2 < 40).astype(np.float32)).expand(1, 3, 32, 32)
            for cx in (15, 17))
    with torch.no_grad():
        moving = XVFILite(width=8, scales=2, flow_init="farneback")(a, b)
        still = XVFILite(width=8, scales=2, flow_init="farneback", still_flow_px=100.0)(a, b)
    np.testing.assert_allclose(still.numpy(), (0.5 * (a + b)).numpy(), atol=1e-5)
    assert float((moving - 0.5 * (a + b)).abs().max()) > 0.1
    # the choice: the best-scoring candidate (a score peaked at 0.5 px), in the order given
    net = XVFILite(width=8, scales=2)
    monkeypatch.setattr(training, "validation_psnr", lambda model, *args: 30 - (model.still_flow_px - 0.5) ** 2)
    scores = training.choose_still_flow(net, None, np.zeros((3, 3), int), "cpu", None, [0.0, 0.25, 0.5, 1.0])
    assert [c for c, _ in scores] == [0.0, 0.25, 0.5, 1.0] and net.still_flow_px == 0.5
    assert training.choose_still_flow(net, None, np.zeros((0, 3), int), "cpu", None, [0.0, 0.5]) == []
    assert net.still_flow_px == 0.0, "without validation triplets: the first candidate"
    with pytest.raises(ValueError, match="interp.still_flow_candidates"):
        training.choose_still_flow(net, None, np.zeros((3, 3), int), "cpu", None, [0.5, -1.0])


def test_the_still_flow_length_is_chosen_per_subject_on_its_kept_frames_only(tmp_path):
    """The interpolation step chooses `still_flow_px` among interp.subject_still_flow_candidates on the subject's own
    triplets of kept frames (0, 2, 4 -> predict 2 from 0 and 4, ...): the best-scoring length is used and reported, a
    held-out frame never changes the choice, and [] keeps the length the network was saved with."""
    from helpers import fake_video_subject, step_cfg
    from PIL import Image

    from avatarlab.preprocess.interp import run
    from avatarlab.preprocess.interp.network import save_interpolator

    folder = fake_video_subject(tmp_path / "s", count=13, size=32)
    save_interpolator(tmp_path / "net.pt", XVFILite(width=8, scales=2, flow_init="farneback", still_flow_px=0.7), 0)
    base = ["scale=smoke", f"preprocess.subject_dir={folder}", f"interp.model={tmp_path / 'net.pt'}",
            "evaluate.st_lpips=false"]
    report = run.interpolate_subject(step_cfg(run, [*base, "interp.subject_still_flow_candidates=[0.0,100.0]"]),
                                     torch.device("cpu"))
    scores = dict(report["still_flow_subject_psnr"])
    assert list(scores) == [0.0, 100.0] and report["still_flow_px_saved"] == 0.7
    assert report["still_flow_px"] == max(scores, key=scores.get)
    assert json.loads((folder / "interp.json").read_text())["still_flow_px"] == report["still_flow_px"]
    # 100 px warps nothing: the untrained network is the cross-fade, scored on the kept triplets' middle frames
    frames = np.stack([np.asarray(Image.open(f), np.float64) / 255 for f in sorted((folder / "frames").glob("*.png"))])
    left, middle, right = frames[0:9:2], frames[2:11:2], frames[4:13:2]
    assert scores[100.0] == pytest.approx(10 * np.log10(1 / np.mean(((left + right) / 2 - middle) ** 2)), abs=0.01)
    # the held-out (odd) frames replaced by black: the choice and its scores are the same, the held-out scores not
    for k in range(1, 13, 2):
        Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(folder / "frames" / f"{k:06d}.png")
    again = run.interpolate_subject(step_cfg(run, [*base, "interp.subject_still_flow_candidates=[0.0,100.0]"]),
                                    torch.device("cpu"))
    assert again["still_flow_subject_psnr"] == report["still_flow_subject_psnr"]
    assert again["xvfi"]["psnr"] != report["xvfi"]["psnr"]
    kept_saved = run.interpolate_subject(step_cfg(run, [*base, "interp.subject_still_flow_candidates=[]"]),
                                         torch.device("cpu"))
    assert kept_saved["still_flow_px"] == 0.7 and kept_saved["still_flow_subject_psnr"] == []
    with pytest.raises(ValueError, match="interp.subject_still_flow_candidates"):
        run.interpolate_subject(step_cfg(run, [*base, "interp.subject_still_flow_candidates=[-1.0]"]),
                                torch.device("cpu"))
    with pytest.raises(ValueError, match="interp.subject_still_flow_candidates"):  # even with nothing to choose on
        run.choose_subject_still_flow(None, None, np.zeros((0, 3), int), [0.5, -1.0], "cpu")


def test_the_interpolator_learns_from_every_video_at_several_speeds_and_never_sees_held_out_frames(tmp_path):
    """One network for all subjects: triplets of every subject's kept frames (even indices) at strides 1 and 2,
    offset into one tensor; the saved weights load back (weights only), anything else stops with a line."""
    from helpers import fake_video_subject, step_cfg

    from avatarlab.preprocess.interp import pretrain
    from avatarlab.preprocess.interp.network import load_interpolator, save_interpolator

    a, b = fake_video_subject(tmp_path / "a", count=9, size=32), fake_video_subject(tmp_path / "b", count=12, size=32)
    frames, triplets, counts, validation = pretrain.gather([a, b], [1, 2])
    assert frames.shape == (21, 3, 32, 32) and counts == {"a": {"frames": 9, "triplets": 4, "validation": 0},
                                                          "b": {"frames": 12, "triplets": 6, "validation": 0}}
    assert validation.shape == (0, 4)
    local = np.where(triplets >= 9, triplets - 9, triplets)
    assert (local % 2 == 0).all(), "only frames variant (b) keeps: the held-out (odd) frames are never trained on"
    assert ((triplets >= 9).all(1) | (triplets < 9).all(1)).all(), "a triplet never mixes two videos"
    assert sorted((t[2] - t[0]) // 2 for t in local.tolist()) == [2] * 7 + [4] * 3  # two motion speeds
    # a motion video is learnt from whole: every frame, neighbours 2 apart (the held-out frames' own gap)
    c = fake_video_subject(tmp_path / "c", count=7, size=32)
    _, whole, counts, _ = pretrain.gather([a], [1], 0, [c])
    assert counts["c"] == {"frames": 7, "triplets": 5, "validation": 0}
    assert whole[whole[:, 0] >= 9].tolist() == [[9 + i, 10 + i, 11 + i] for i in range(5)]
    cfg = step_cfg(pretrain, ["scale=smoke", f"interp.subject_dirs=[{a},{b}]", f"interp.out_dir={tmp_path / 'out'}",
                              "interp.iterations=3", "interp.width=8", "interp.scales=2",
                              "interp.strides=[1,2]", "interp.still_flow_candidates=[0.0,0.25,0.5,1.0]"])
    pretrain.train_interpolator(cfg, torch.device("cpu"))
    report = json.loads((tmp_path / "out" / "train.json").read_text())
    # validation_every=5: each video's third triplet ([4, 6, 8]) chooses the snapshot, and no training triplet keeps
    # its middle frame as a target (a: 4 - 1 = 3; b: 6 - 1 - [2, 6, 10] = 4)
    assert report["subjects"]["a"] == {"frames": 9, "triplets": 3, "validation": 1}
    assert report["subjects"]["b"] == {"frames": 12, "triplets": 4, "validation": 1}
    assert report["iterations"] == 3 and report["triplets"] == 7 and not (tmp_path / "out" / "checkpoint.pt").exists()
    assert [step for step, _ in report["validation_psnr_curve"]] == [0, 3]  # before training, at the checkpoint
    assert report["chosen_validation_psnr"] == max(v for _, v in report["validation_psnr_curve"])
    trained = load_interpolator(tmp_path / "out" / "model.pt")
    assert trained.width == 8 and not trained.keep_unwarped  # conf/config.yaml's default
    # the still-flow length: each candidate scored on the validation triplets, the best kept
    scores = report["still_flow_validation_psnr"]
    assert [c for c, _ in scores] == [0.0, 0.25, 0.5, 1.0]
    assert trained.still_flow_px == report["still_flow_px"] == max(scores, key=lambda cs: cs[1])[0]
    net = XVFILite(width=8, scales=2, keep_unwarped=True, still_flow_px=0.4)
    with torch.no_grad():
        net.synthesis.keep.fill_(0.03)
    save_interpolator(tmp_path / "net.pt", net, 3)
    again = load_interpolator(tmp_path / "net.pt")
    assert again.keep_unwarped and float(again.synthesis.keep) == pytest.approx(0.03) and again.still_flow_px == 0.4
    for p, q in zip(net.parameters(), again.parameters(), strict=True):
        torch.testing.assert_close(p, q)
    older = {k: v for k, v in torch.load(tmp_path / "net.pt", weights_only=True).items()
             if k not in ("keep_unwarped", "still_flow_px")}
    older["state"] = XVFILite(width=8, scales=2).state_dict()  # a network saved before either setting existed
    torch.save(older, tmp_path / "older.pt")
    assert not load_interpolator(tmp_path / "older.pt").keep_unwarped
    assert load_interpolator(tmp_path / "older.pt").still_flow_px == 0.0  # every pixel warped, as it was
    torch.save({"format": "other"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="bad.pt: not an avatarlab frame interpolator"):
        load_interpolator(tmp_path / "bad.pt")


def test_interpolation_never_spans_a_cut_between_two_clips(tmp_path):
    """A subject of several recordings: no training triplet and no held-out frame has neighbours from two clips (a
    cut has no motion to interpolate), and the experiment's report scores only the frames inside one clip."""
    from helpers import fake_video_subject

    from avatarlab.preprocess.interp import pretrain
    from avatarlab.preprocess.interp.training import split_variants, training_triplets

    clips = np.array([0] * 5 + [1] * 6)  # frames 0-4 one recording, 5-10 another
    kept, held = split_variants(11, clips)
    assert kept.tolist() == [0, 2, 4, 6, 8, 10] and held.tolist() == [1, 3, 7, 9]  # not 5: frames 4 and 6 straddle
    assert split_variants(11)[1].tolist() == [1, 3, 5, 7, 9]
    assert training_triplets(kept, (1, 2), clips).tolist() == [[0, 2, 4], [6, 8, 10]]
    assert len(training_triplets(kept, (1, 2))) == 6
    folder = fake_video_subject(tmp_path / "two_clips", count=11, size=32, clips=clips.tolist())
    _, triplets, counts, _ = pretrain.gather([folder], [1, 2])
    assert triplets.tolist() == [[0, 2, 4], [6, 8, 10]] and counts["two_clips"]["triplets"] == 2


def test_the_interpolators_validation_triplets_do_not_depend_on_the_strides_it_trains_on():
    """The stride is a choice made on validation triplets, so every stride setting is scored on the same stride-1
    triplets, and none of them is a training target at any stride; at strides [1] the split is the plain one."""
    from avatarlab.preprocess.interp.pretrain import split_by_stride_one
    from avatarlab.preprocess.interp.training import training_triplets, validation_split

    kept = np.arange(0, 60, 2)
    found_1, held_1 = split_by_stride_one(kept, [1], None, 5)
    found_123, held_123 = split_by_stride_one(kept, [1, 2, 3], None, 5)
    assert held_1.tolist() == held_123.tolist() and len(held_1) == 6
    assert (held_1[:, 2] - held_1[:, 0] == 4).all()  # stride 1: neighbours 4 frames apart among the kept frames
    for found in (found_1, found_123):
        assert not np.isin(found[:, 1], held_1[:, 1]).any()
    assert len(found_123) > len(found_1) and {int(r - l) for l, _, r in found_123} == {4, 8, 12}
    plain, plain_held = validation_split(training_triplets(kept, (1,)), 5)
    assert found_1.tolist() == plain.tolist() and held_1.tolist() == plain_held.tolist()


def test_the_interpolators_paired_gain_is_a_gain_only_beyond_its_ci():
    from scipy import stats

    from avatarlab.preprocess.interp.run import frame_psnr, paired_gain

    target = torch.full((3, 3, 4, 4), 0.5)
    pred = target.clone()
    pred[0] += 0.1  # MSE 0.01: 20 dB
    pred[1] += 0.01  # 40 dB
    pred[2] += 0.001  # 60 dB
    np.testing.assert_allclose(frame_psnr(pred, target), [20, 40, 60], atol=1e-3)
    rng = np.random.default_rng(0)
    base = rng.normal(30, 2, 40)
    model = base + 0.5 + rng.normal(0, 0.1, 40)
    better = paired_gain(model, base)
    assert better["verdict"] == "better" and better["wins"] >= 38 and abs(better["mean_db"] - 0.5) < 0.05
    assert 0 < better["ci95_db"] < 0.1
    low, high = stats.ttest_1samp(model - base, 0.0).confidence_interval(0.95)  # Student's t over the 40 frames
    assert better["ci95_db"] == pytest.approx((high - low) / 2, rel=1e-9)
    noisy = paired_gain(base + rng.normal(0, 1.0, 40), base)
    assert noisy["verdict"] == "within the frames' spread" and noisy["ci95_db"] > abs(noisy["mean_db"])
    assert paired_gain(base - 1, base)["verdict"] == "worse"


def test_interpolation_training_resumes_to_the_same_result(tmp_path):
    from omegaconf import OmegaConf

    from avatarlab.preprocess.interp.training import train, training_triplets, validation_psnr

    cfg = OmegaConf.merge(interp_config(), {"interp": {"checkpoint_every": 1, "lr": 3e-2}})
    frames = torch.rand(9, 3, 16, 16)
    triplets = training_triplets(np.arange(0, 9, 2))
    held = triplets[1:2]  # scores the snapshots (a test of the bookkeeping, not of generalisation)
    full, _, chosen = train(frames, triplets, cfg, tmp_path / "full.pt", validation=held)
    # "killed" after 3 steps: a checkpoint at step 3 exists; the rerun resumes from it
    cfg_short = OmegaConf.merge(cfg, {"interp": {"iterations": 3}})
    train(frames, triplets, cfg_short, tmp_path / "resumed.pt", validation=held)
    state = torch.load(tmp_path / "resumed.pt", weights_only=True)
    state["fingerprint"] = state["fingerprint"].replace("iterations: 3", "iterations: 6")
    torch.save(state, tmp_path / "resumed.pt")
    resumed, losses, again = train(frames, triplets, cfg, tmp_path / "resumed.pt", validation=held)
    assert len(losses) == 6 and again == chosen
    for p, q in zip(full.parameters(), resumed.parameters()):
        torch.testing.assert_close(p, q)
    assert [step for step, _ in chosen["curve"]] == list(range(7))
    assert chosen["best_psnr"] == max(v for _, v in chosen["curve"])
    assert len({round(v, 6) for _, v in chosen["curve"]}) > 1, "training moved the network"
    assert validation_psnr(full, frames, held, torch.device("cpu")) == pytest.approx(chosen["best_psnr"], abs=1e-4)
    for mode in (True, False):  # scoring leaves the network in the mode it found it in
        full.train(mode)
        validation_psnr(full, frames, held, torch.device("cpu"))
        assert full.training is mode


def test_interpolation_training_loss_is_l1_or_the_squared_error(tmp_path):
    """interp.loss: the first step's loss is the untrained network's mean |error| (l1, XVFI's) or mean squared error
    (l2) on the batch the seed draws; anything else stops before training."""
    from omegaconf import OmegaConf

    from avatarlab.preprocess.interp.network import XVFILite
    from avatarlab.preprocess.interp.training import train, training_triplets

    frames = torch.rand(9, 3, 16, 16)
    triplets = training_triplets(np.arange(0, 9, 2))
    cfg = OmegaConf.merge(interp_config(), {"interp": {"iterations": 1, "keep_unwarped": False}})
    rng = np.random.default_rng(0)  # the draws train() makes for its first batch
    pick = triplets[rng.integers(0, len(triplets), 2)]
    a, mid, b = (frames[pick[:, k]] for k in range(3))
    if rng.random() < 0.5:
        a, b = b, a
    if rng.random() < 0.5:
        a, mid, b = (x.flip(-1) for x in (a, mid, b))
    with torch.no_grad():
        error = XVFILite(8, 2, "farneback")(a, b, 0.5) - mid
    firsts = {}
    for kind in ("l1", "l2"):
        _, losses, _ = train(frames, triplets, OmegaConf.merge(cfg, {"interp": {"loss": kind}}), tmp_path / f"{kind}.pt")
        firsts[kind] = losses[0]
    assert firsts["l1"] == pytest.approx(float(error.abs().mean()), rel=1e-5)
    assert firsts["l2"] == pytest.approx(float(error.square().mean()), rel=1e-5)
    with pytest.raises(ValueError, match="interp.loss"):
        train(frames, triplets, OmegaConf.merge(cfg, {"interp": {"loss": "huber"}}), tmp_path / "bad.pt")


def _rgbd_truth(head_model: HeadModel, seed: int = 3) -> dict:
    """One synthetic RGBD frame of a non-mean identity, in the layout of a synthetic subject's truth.npz."""
    rng = np.random.default_rng(seed)
    params = head_model.zeros(1)
    params["shape"][0] = torch.from_numpy(np.clip(rng.normal(0, 1.0, head_model.n_shape), -2, 2)).float()
    params["pose"][0, 6] = 0.2
    cam = orbit_camera(1.0, 10.0, 0.0, image_size=(192, 192))
    with torch.no_grad():
        out = HeadRenderer(head_model)(params, cam)
    return {"depth": out.depth[:, 0].numpy(), "masks": (out.mask[:, 0].numpy() > 0.5),
            "landmarks2d": out.landmarks2d.numpy(), "K": cam.K.numpy(), "R": cam.R.numpy(), "t": cam.t.numpy(),
            "shape": params["shape"][0].numpy(), "expression": params["expression"].numpy(),
            "pose": params["pose"].numpy()}, [(out.rgb[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)]


def test_rgbd_fit_reaches_the_depth_noise_floor(head_model):
    """Blocks 1-3 with the configured weights land within 1.3x of the noise floor (what the true mesh scores on the
    same noisy cloud); the old settings (a 1e-5 prior that outweighed block 3's ~1e-6 m^2 loss, w2 = 1e3, a
    constant rate) stopped at about twice it."""
    from omegaconf import OmegaConf

    from avatarlab.preprocess.fit_rgbd import RGBDFitter, fit_one_frame

    truth, video = _rgbd_truth(head_model)
    settings = compose_config(["scale=tiny"]).fit_rgbd
    fit = OmegaConf.merge(settings, {"detected_landmarks": False, "texture_iterations": 0})
    scores = {}
    for name, fitter in {"configured": RGBDFitter(head_model, float(fit.lr), tuple(fit.block_weights),
                                                  float(fit.prior_weight), bool(fit.cosine_decay)),
                         "old": RGBDFitter(head_model, float(fit.lr), (1.0, 1000.0), 1e-5, False)}.items():
        scores[name] = fit_one_frame(head_model, fitter, fit, truth, video, 0, np.random.default_rng(0), "cpu")
    new, old = scores["configured"], scores["old"]
    assert 0.5 < new["noise_floor_mm"] < 1.5  # 1 mm depth noise
    assert new["accuracy_mm"] < 1.3 * new["noise_floor_mm"], new
    assert old["accuracy_mm"] > 1.5 * old["noise_floor_mm"], old
    assert new["shape_error_mm"] < old["shape_error_mm"]


def test_the_rgb_fit_keeps_the_jaw_within_its_limits(head_model):
    """A frame whose landmarks pull the jaw the closed way (as a bad local minimum did: -48 degrees on a talking
    video's last frames) is fitted with the jaw at the limit, not beyond it; without limits it goes past it."""
    size = 64
    camera = orbit_camera(0.6, image_size=(size, size), batch=2)
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    from avatarlab.render.lighting import default_lighting

    params = head_model.zeros(2)
    target_pose = params["pose"].clone()
    target_pose[:, 6] = -0.6  # a jaw turned 34 degrees the closed way: what the landmarks will ask for
    state = {"shape": params["shape"][:1], "texture": params["texture"][:1], "lighting": default_lighting(1),
             "focal": camera.K[:1, 0, 0].log(), "expression": params["expression"], "pose": params["pose"],
             "rot": rotation_matrix_to_axis_angle(camera.R), "trans": camera.t}
    limits = (np.radians(-6.0), np.radians(40.0))
    fitted = {}
    for name, jaw_limits in (("limited", limits), ("free", None)):
        fitter = RGBFitter(head_model, size, FitWeights(photometric=0.0), 0.02, (0.35, 0.45, 0.55), jaw_limits)
        with torch.no_grad():
            target = fitter.render(**dict(state, pose=target_pose))[0]
        out, _ = fitter.optimize(target.rgb, target.landmarks2d, target.mask, torch.ones(2), state, {"pose"}, 150, 0)
        fitted[name] = out["pose"][:, 6]
    assert torch.all(fitted["limited"] >= limits[0] - 1e-6), fitted["limited"]
    assert torch.allclose(fitted["limited"], torch.full((2,), limits[0], dtype=torch.float32), atol=1e-3)
    assert torch.all(fitted["free"] < limits[0] - 0.05), fitted["free"]  # the limit is what held it
