"""Units of the avatar experiments, the applications and the report (the workflow test runs them end to end)."""
import csv

import numpy as np
import pytest
import torch

from avatarlab.avatar.telepresence import payload
from avatarlab.data.real_images import replace_with_interpolated, z_augment
from avatarlab.model.avatar import orbit
from avatarlab.render.camera import Camera
from avatarlab.report.build import PUBLISHED_TABLE2, Table, comparison_table, final_avatar_table, interp_table


def test_recreated_frames_take_the_interpolated_image_and_the_neighbours_mean(tmp_path):
    n = 5
    frames = np.zeros((n, 8, 8, 3), np.uint8)
    masks = np.zeros((n, 8, 8), np.uint8)
    masks[0, :4] = 1
    masks[2, 4:] = 1
    angle = np.radians(20)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    fit = {"fitted": np.array([True, True, True, False, True]),
           "shape": np.zeros((n, 3)), "texture": np.zeros((n, 2)), "lighting": np.zeros((n, 9, 3)),
           "expression": np.arange(n, dtype=float)[:, None].repeat(4, 1), "pose": np.zeros((n, 15)),
           "K": np.tile(np.eye(3), (n, 1, 1)), "R": np.stack([np.eye(3), np.eye(3), rot, np.eye(3), np.eye(3)]),
           "t": np.arange(n, dtype=float)[:, None].repeat(3, 1)}
    fit["expression"][1] = 99.0  # the real fit of a re-created frame must not leak in
    done = replace_with_interpolated(frames, masks, fit, np.array([1, 3]), np.full((2, 8, 8, 3), 200, np.uint8))
    assert list(done) == [1, 3]
    assert (frames[1] == 200).all() and (frames[0] == 0).all()
    assert masks[1].sum() == 64 and masks[1][:4].all() and masks[1][4:].all()  # union of the neighbours
    assert fit["expression"][1] == pytest.approx([1.0] * 4) and fit["t"][1] == pytest.approx([1.0] * 3)
    R = fit["R"][1]
    assert R @ R.T == pytest.approx(np.eye(3), abs=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(10.0, abs=1e-6)  # halfway rotation
    assert fit["fitted"][3]  # frame 3 was not fitted, its neighbours 2 and 4 were: it is re-created
    with pytest.raises(ValueError, match="interpolated frames are"):
        replace_with_interpolated(frames, masks, fit, np.array([1]), np.zeros((1, 4, 4, 3), np.uint8))


def test_novel_view_orbit_and_telepresence_payload():
    cam = Camera(K=torch.eye(3)[None], R=torch.eye(3)[None], t=torch.tensor([[0.0, 0.0, 1.0]]), image_size=(64, 64))
    same = orbit(cam, 0.0)
    assert torch.allclose(same.R, cam.R) and torch.allclose(same.t, cam.t)
    turned = orbit(cam, 30.0, dz=0.1)
    point = turned.world_to_camera(torch.tensor([[[0.0, 0.0, 0.1]]]))[0, 0]
    assert point[0] == pytest.approx(0.1 * np.sin(np.radians(30)), abs=1e-6)  # the head turned by 30 degrees
    assert point[2] == pytest.approx(1.1 + 0.1 * np.cos(np.radians(30)), abs=1e-6)  # and moved 0.1 away
    params = {"pose": torch.zeros(3, 15), "expression": torch.zeros(3, 50)}
    message = payload(params, torch.eye(3).expand(3, 3, 3), torch.zeros(3, 3))
    assert message.shape == (3, 12 + 50 + 6)


def test_z_augmentation_moves_the_head_along_the_optical_axis(head_model):
    """Zooming the image by s about the principal point is what the camera sees when the head's camera-space z
    becomes z / s: the landmarks projected with the augmented camera land where the zoom put them."""
    from avatarlab.render.camera import orbit_camera

    cam = orbit_camera(torch.ones(1), 5.0, 3.0, image_size=(64, 64), focal=180.0)
    cam.t[:, 0] += 0.02  # the head off the optical axis too
    with torch.no_grad():
        lm = head_model(*[v for k, v in head_model.zeros(1).items() if k != "texture"]).landmarks3d
    g = torch.Generator().manual_seed(0)
    images = torch.zeros(1, 3, 64, 64)
    _, _, moved = z_augment(images, torch.ones(1, 1, 64, 64), cam, g, 1.2, 1.2, p=1.0)
    before, after = cam.project(lm)[0, :, :2], moved.project(lm)[0, :, :2]
    centre = cam.K[0, :2, 2]
    expected = centre + (before - centre) * 1.2
    assert moved.t[0, 2] == pytest.approx(float(cam.t[0, 2]) / 1.2) and torch.equal(moved.K, cam.K)
    assert (after - expected).norm(dim=-1).max() < 0.02 * 64, "within the perspective change over the head's depth"


def avatar(subject, recipe, init, variant, psnr, best=20.0, lpips=None, seconds=30.0):
    scores = {"psnr": psnr, "psnr_head": psnr - 5, "ssim": 0.8, "lpips": lpips, "st_lpips": 0.3,
              "face_detection_rate": 1.0, "landmark_nme": 0.05, "identity_similarity": 0.9}
    base = {"last_frame": dict(scores, psnr=best), "mean_frame": dict(scores, psnr=best - 1)}
    part = {"frames": 3, "model": scores, "baselines": base,
            "gain": {"psnr": {"best_baseline": "last_frame", "baseline": best, "gain": psnr - best,
                              "beats": psnr > best}}}
    return {"subject": subject, "recipe": recipe, "init": init, "variant": variant, "seed": 0,
            "train": {"train_seconds": seconds},
            "eval": {"all": part, "mouth_open": part, "render_seconds_per_frame": 0.01, "frames_variant": variant}}


def test_report_tables_carry_baselines_label_published_rows_and_never_invent_numbers(tmp_path):
    avatars = [avatar("s", "final", "beta6_from_alpha2", "a", 24.0), avatar("s", "base", "beta6_from_alpha2", "a", 19.0),
               avatar("s", "base", "beta6_from_alpha2", "b", 23.0), avatar("s", "base", "beta6_from_alpha2", "c", 23.5)]
    table = comparison_table(avatars, "beta6_from_alpha2", "tiny")
    assert [r["source"] for r in table.rows] == ["published"] * len(PUBLISHED_TABLE2) + ["this run"]
    assert table.rows[-1]["psnr"] == 24.0 and table.rows[-1]["lpips"] is None
    assert table.rows[-1]["best_baseline_psnr"] == "20.00 (last_frame)"
    md = table.markdown()
    assert "| published | proposed (dissertation) | INSTA, 256x256 | 26.29 | 0.895 | 0.046 |" in md
    assert table.csv().count("26.2867") == 1  # the CSV keeps every digit
    assert "| this run |" in md and "missing" in md
    interp = interp_table(avatars, "beta6_from_alpha2")
    assert [r["variant"] for r in interp.rows] == ["a", "b", "c"]
    assert interp.rows[2]["gain_c_over_b_db"] == pytest.approx(0.5)
    assert "1 of 3 rows do NOT beat their best trivial baseline: s / a" in interp.note
    assert interp.sentence() == ("s / a does NOT beat its best baseline (last_frame) (-1.00); s / b beats its best "
                                 "baseline (last_frame) by 3.00 (one run: no noise estimate); s / c beats its best "
                                 "baseline (last_frame) by 3.50 (one run: no noise estimate).")
    interp.write(tmp_path)
    with open(tmp_path / "interpolation.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["lpips"] == "" and float(rows[2]["gain_c_over_b_db"]) == pytest.approx(0.5)
    finals, per_predictor = final_avatar_table(avatars, "beta6_from_alpha2")
    assert len(finals.rows) == 1 and "Every row (1) beats its best trivial baseline" in finals.note
    assert [r["predictor"] for r in per_predictor.rows] == ["model", "last_frame", "mean_frame"]
    empty = Table("t", "T", ["a", "b"])
    assert "(no runs)" in empty.markdown()


def test_the_sharpness_table_puts_every_seed_beside_the_nearest_training_frame():
    """The card's bar for a sharp avatar: its ST-LPIPS over seeds against the copied nearest frame's (gain =
    nearest - avatar with its CI, how many seeds are below); the face table scores the same renders with dlib:
    landmark error and identity beside the mean and nearest frames'."""
    from avatarlab.report.avatar_tables import face_table, sharpness_table

    avatars = []
    for seed, (st, identity, nme) in enumerate([(0.15, 0.93, 0.10), (0.17, 0.95, 0.12), (0.22, 0.94, None)]):
        a = avatar("obama", "final", "beta6_from_alpha2", "a", 22.0)
        a["seed"] = seed
        part = a["eval"]["all"]
        part["model"] = dict(part["model"], st_lpips=st, identity_similarity=identity, landmark_nme=nme,
                             face_detection_rate=0.0 if nme is None else 1.0)
        part["baselines"] = dict(part["baselines"], nearest=dict(part["model"], st_lpips=0.19, identity_similarity=0.96,
                                                                 landmark_nme=0.15),
                                 mean_frame=dict(part["model"], identity_similarity=0.92, landmark_nme=0.13))
        avatars.append(a)
    blurred = avatar("talk", "final", "beta6_from_alpha2", "a", 28.0)  # 0.3 against a nearest frame of 0.02
    blurred["eval"]["all"]["baselines"]["nearest"] = dict(blurred["eval"]["all"]["model"], st_lpips=0.02)
    blurred["eval"]["all"]["model"] = {k: v for k, v in blurred["eval"]["all"]["model"].items()
                                       if k not in ("face_detection_rate", "landmark_nme", "identity_similarity")}
    others = [blurred, avatar("s", "base", "alpha1", "a", 20.0)]
    table = sharpness_table(avatars + others, "beta6_from_alpha2")
    obama, talk = table.rows
    assert obama["seeds"] == 3 and obama["seeds_below_nearest"] == "2 of 3"
    assert obama["st_lpips"] == pytest.approx(0.18) and obama["nearest_st_lpips"] == 0.19
    assert obama["gain"] == pytest.approx(0.01) and obama["gain_ci95"] > 0.01, "one seed above: within the noise"
    assert talk["seeds_below_nearest"] == "0 of 1" and talk["gain"] == pytest.approx(-0.28)
    sentence = table.sentence()
    assert sentence == ("obama is ahead of the nearest training frame in ST-LPIPS by 0.010, within the noise (95 % CI "
                        "±0.090); talk does NOT beat the nearest training frame in ST-LPIPS (-0.280).")
    faces = face_table(avatars + others, "beta6_from_alpha2")
    assert [r["subject"] for r in faces.rows] == ["obama"], "a subject without dlib scores has no face row"
    obama = faces.rows[0]
    assert obama["face_detection_rate"] == pytest.approx(2 / 3), "the seed where dlib found no face counts"
    assert obama["landmark_nme"] == pytest.approx(0.11), "NME over the seeds with a face found"
    assert obama["mean_frame_nme"] == 0.13 and obama["nearest_nme"] == 0.15
    assert obama["nme_gain"] == pytest.approx(0.04) and obama["nme_gain_ci95"] is not None
    assert obama["identity_similarity"] == pytest.approx(0.94) and obama["mean_frame_identity"] == 0.92
    assert obama["nearest_identity"] == 0.96
    shown, _ = faces.visible()
    assert shown == ["subject", "face_detection_rate", "landmark_nme", "mean_frame_nme", "nearest_nme",
                     "identity_similarity", "mean_frame_identity", "nearest_identity"]
    assert faces.sentence().startswith("obama is ahead of the nearest training frame in landmark error by 0.04")


def test_the_fit_table_puts_the_trained_frames_beside_the_test_frames_for_every_seed():
    """eval.json's `trained` (the avatar on its own training frames) beside its test scores: the gap trained - test
    with its CI over seeds; a subject evaluated without trained frames has no row."""
    from avatarlab.report.avatar_tables import fit_table

    avatars = []
    for seed, (trained, test) in enumerate([(28.0, 23.0), (29.0, 23.5), (28.5, 22.5)]):
        a = avatar("obama", "final", "beta6_from_alpha2", "a", test)
        a["seed"] = seed
        a["eval"]["trained"] = {"frames": 24, "indices": list(range(24)),
                                "model": {"psnr": trained, "ssim": 0.87, "st_lpips": 0.1}}
        avatars.append(a)
    unscored = avatar("talk", "final", "beta6_from_alpha2", "a", 30.0)  # evaluated with trained_frames = 0
    unscored["eval"]["trained"] = None
    table = fit_table(avatars + [unscored, avatar("s", "base", "alpha1", "a", 20.0)], "beta6_from_alpha2")
    assert [r["subject"] for r in table.rows] == ["obama"]
    row = table.rows[0]
    assert row["seeds"] == 3 and row["trained_frames"] == 24
    assert row["trained_psnr"] == pytest.approx(28.5) and row["psnr"] == pytest.approx(23.0)
    assert row["gap_psnr"] == pytest.approx(5.5) and 0 < row["gap_psnr_ci95"] < 5.5
    assert row["gap_ssim"] == pytest.approx(0.07) and row["trained_st_lpips"] == pytest.approx(0.1)


def test_the_same_recording_table_scores_later_frames_of_the_training_recordings_beside_their_baselines():
    """eval.json's `same_recording` (the last frames of the training clips, held out) over seeds, with its own
    baselines and the held-out clips' scores beside it; a subject without such frames (synthetic: its test frames
    are already its recording's last) has no row."""
    from avatarlab.report.avatar_tables import same_recording_table

    avatars = []
    for seed, (later, unseen) in enumerate([(27.0, 22.0), (27.5, 23.0), (28.0, 24.0)]):
        a = avatar("obama", "final", "beta6_from_alpha2", "a", unseen)
        a["seed"] = seed
        part = avatar("obama", "final", "beta6_from_alpha2", "a", later, best=25.0)["eval"]["all"]
        part["frames"] = 20
        part["baselines"]["nearest"] = dict(part["model"], psnr=25.0, st_lpips=0.04, identity_similarity=0.99)
        part["model"] = dict(part["model"], st_lpips=0.05 + 0.01 * seed)
        a["eval"]["same_recording"] = part
        avatars.append(a)
    table = same_recording_table(avatars + [avatar("talk", "final", "beta6_from_alpha2", "a", 30.0),
                                            avatar("s", "base", "alpha1", "a", 20.0)], "beta6_from_alpha2")
    assert [r["subject"] for r in table.rows] == ["obama"]
    row = table.rows[0]
    assert row["seeds"] == 3 and row["test_frames"] == 20 and row["best_baseline"] == "last_frame"
    assert row["psnr"] == pytest.approx(27.5) and row["baseline_psnr"] == 25.0
    assert row["gain"] == pytest.approx(2.5) and 0 < row["gain_ci95"] < 2.5
    assert row["st_lpips"] == pytest.approx(0.06) and row["nearest_st_lpips"] == 0.04
    assert row["nearest_identity"] == 0.99 and row["unseen_recordings_psnr"] == pytest.approx(23.0)
    assert table.sentence().startswith("obama beats its best baseline (last_frame) by 2.5")


def test_a_table_shows_eight_columns_rounded_to_its_noise_and_says_which_row_is_best():
    """What a reader sees: at most 8 columns (the others named, all in the CSV), a value with its CI rounded to the
    CI's first significant digit + 1, the best row marked, and one sentence on whether it beats its baseline beyond
    the noise."""
    from avatarlab.report.table import Headline, rounded

    columns = ["model", "psnr", "psnr_ci95", "best_baseline", "gain", "gain_ci95"] + [f"x{i}" for i in range(6)]
    table = Table("t", "T", columns, "a note", headline=Headline("psnr", ("model",)))
    table.add(model="a", psnr=23.4567, psnr_ci95=0.123, best_baseline="last_frame", gain=0.4321, gain_ci95=0.6,
              **{f"x{i}": float(i) for i in range(6)})
    table.add(model="b", psnr=24.9876, psnr_ci95=0.0456, best_baseline="last_frame", gain=1.9876, gain_ci95=0.0456,
              **{f"x{i}": float(i) for i in range(6)})
    md = table.markdown()
    header = next(line for line in md.splitlines() if line.startswith("| model"))
    assert header.count("|") - 1 == 8 and "x5" not in header
    assert "More columns in `t.csv`: x4, x5." in md
    assert "| **b** (best) | 24.988 ± 0.046 | last_frame | 1.988 ± 0.046 |" in md
    assert "| a | 23.46 ± 0.12 | last_frame | 0.43 ± 0.60 |" in md
    assert table.sentence() == ("Best by psnr (higher is better): b (24.988); b beats its best baseline (last_frame) "
                                "by 1.988, beyond the 95 % CI (±0.046).")
    table.rows[1]["gain"] = 0.02
    assert "within the noise" in table.sentence()
    table.rows[1]["gain"] = -0.5
    assert "does NOT beat its best baseline (last_frame)" in table.sentence()
    page = table.html()
    assert '<tr class="best"><td><b>b</b> (best)</td>' in page and "<th>x3</th>" in page and "<th>x4</th>" not in page
    assert "24.9876" in table.csv() and rounded(0.000123) == "0.000123" and rounded(1234.56) == "1234.6"
    assert rounded(None) == "missing" and rounded(float("nan")) == "not finite"
