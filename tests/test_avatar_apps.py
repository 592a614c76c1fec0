"""Units of the avatar experiments, the applications and the report (the workflow test runs them end to end)."""
import csv

import numpy as np
import pytest
import torch

from avatarlab.apps.avatar import orbit
from avatarlab.apps.telepresence import payload
from avatarlab.evaluate.report import PUBLISHED_TABLE2, Table, comparison_table, interp_table
from avatarlab.render.camera import Camera
from avatarlab.train.finetune import split
from avatarlab.train.pretrain import replace_with_interpolated


def test_interpolation_variants_of_the_training_split():
    fitted = np.ones(20, bool)
    fitted[4] = False
    a, test = split(20, fitted, 6, "a")
    b, test_b = split(20, fitted, 6, "b")
    c, test_c = split(20, fitted, 6, "c", interpolated=[1, 3, 5, 7, 9, 11, 13, 15, 17])
    assert list(test) == list(test_b) == list(test_c) == [14, 15, 16, 17, 18, 19]
    assert list(b) == [0, 2, 6, 8, 10, 12]  # even, fitted, before the test frames
    assert list(c) == [0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12, 13]  # + re-created odd ones, none from the test part
    with pytest.raises(ValueError, match="frames_variant"):
        split(20, fitted, 6, "d")


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
    path = tmp_path / "interpolated.npz"
    np.savez(path, indices=np.array([1, 3]), frames=np.full((2, 8, 8, 3), 200, np.uint8), kept=np.array([0, 2, 4]))
    done = replace_with_interpolated(frames, masks, fit, path)
    assert list(done) == [1, 3]
    assert (frames[1] == 200).all() and (frames[0] == 0).all()
    assert masks[1].sum() == 64 and masks[1][:4].all() and masks[1][4:].all()  # union of the neighbours
    assert fit["expression"][1] == pytest.approx([1.0] * 4) and fit["t"][1] == pytest.approx([1.0] * 3)
    R = fit["R"][1]
    assert R @ R.T == pytest.approx(np.eye(3), abs=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(10.0, abs=1e-6)  # halfway rotation
    assert fit["fitted"][3]  # frame 3 was not fitted, its neighbours 2 and 4 were: it is re-created
    with pytest.raises(ValueError, match="interpolated frames are"):
        np.savez(path, indices=np.array([1]), frames=np.zeros((1, 4, 4, 3), np.uint8), kept=np.array([0]))
        replace_with_interpolated(frames, masks, fit, path)


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


def run(subject, init, variant, psnr, lpips=None, seconds=30.0):
    part = {"frames": 3, "psnr": psnr, "ssim": 0.8, "lpips": lpips, "identity_similarity": None}
    return {"subject": subject, "init": init, "frames_variant": variant, "train_frames": 9, "iterations": 5,
            "train_seconds": seconds, "test": {"all": part, "mouth_open": part, "render_seconds_per_frame": 0.01}}


def test_report_tables_label_published_rows_and_never_invent_numbers(tmp_path):
    avatars = [run("s", "beta6_from_alpha2", "a", 24.0), run("s", "beta6_from_alpha2", "b", 23.0),
               run("s", "beta6_from_alpha2", "c", 23.5), run("s", "alpha1", "a", 22.0)]
    table = comparison_table(avatars, "beta6_from_alpha2", "tiny")
    assert [r["source"] for r in table.rows] == ["published"] * len(PUBLISHED_TABLE2) + ["this run"]
    assert table.rows[-1]["psnr"] == 24.0 and table.rows[-1]["lpips"] is None
    md = table.markdown()
    assert "| published | proposed (dissertation) | INSTA, 256x256 | 26.2867 | 0.8952 | 0.0461 |" in md
    assert "| this run |" in md and "missing" in md
    interp = interp_table(avatars, tmp_path)
    assert [r["variant"] for r in interp.rows] == ["a", "b", "c"]
    assert interp.rows[2]["gain_c_over_b_db"] == pytest.approx(0.5)
    interp.write(tmp_path)
    with open(tmp_path / "interpolation.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["lpips"] == "" and float(rows[2]["gain_c_over_b_db"]) == pytest.approx(0.5)
    empty = Table("t", "T", ["a", "b"])
    assert "(no runs)" in empty.markdown()
