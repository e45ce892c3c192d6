"""Synthetic sequences: random poses and thesis motions rendered into the sequence layout."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from torchhand.data.layout import frame_name, read_depth, read_poses, read_rgb, read_sequence_info, read_init_pose
from torchhand.data.synth import SyntheticFrames, random_poses, shade_rgb, thesis_motion, write_synthetic_sequence
from torchhand.geometry.render import RenderResult, render
from torchhand.model.scene import Scene

N = 3


@pytest.fixture(scope="module")
def frames():
    return random_poses(["hand_right"], N, seed=0)


@pytest.fixture(scope="module")
def seq(frames, tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "seq"
    ret = write_synthetic_sequence(frames, out, noise="none", progress=False)
    assert ret == out
    return out


@pytest.fixture(scope="module")
def fresh(seq):
    """A fresh render of the written ground-truth poses, from the written camera."""
    info = read_sequence_info(seq)
    gt = read_poses(seq / "gt")
    scene = Scene.from_names(info.models, dtype=torch.float64)
    cam = info.cameras[0].to(dtype=torch.float64)
    with torch.no_grad():
        posed = scene(torch.as_tensor(gt.theta))
    res = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    return scene, cam, posed, res


def _one(frames: SyntheticFrames, n=1) -> SyntheticFrames:
    return dataclasses.replace(frames, theta=frames.theta[:n])


# ------------------------------------------------------------------ random poses
def test_random_poses_shape_limits_and_seed():
    a = random_poses(["hand_right"], 3, seed=0)
    b = random_poses(["hand_right"], 3, seed=0)
    c = random_poses(["hand_right"], 3, seed=1)
    assert a.scene.names == ["hand_right"] and a.theta.shape == (3, a.scene.num_dofs)
    assert a.theta.dtype == torch.float64
    assert torch.equal(a.theta, b.theta)
    assert not torch.equal(a.theta, c.theta)
    lo, hi = a.scene.lower, a.scene.upper
    finite = torch.isfinite(lo) & torch.isfinite(hi)
    assert bool(((a.theta >= lo) | ~finite).all()) and bool(((a.theta <= hi) | ~finite).all())
    assert len(a.cameras) == 1 and a.source["seed"] == 0


def test_random_poses_vertex_centroid_within_distance_range():
    f = random_poses(["hand_right"], 4, seed=3, distance=(500.0, 600.0))
    with torch.no_grad():
        v = f.scene(f.theta).vertices
    z = v.mean(1)[:, 2]  # the rest-pose centroid is placed; finger angles move it a little
    assert bool(((z > 500 - 30) & (z < 600 + 30)).all()), z


# ------------------------------------------------------------------ written layout
def test_folder_has_the_documented_files(seq):
    names = {str(p.relative_to(seq)) for p in seq.rglob("*") if p.is_file()}
    expected = {"sequence.json", "init_pose.json", "gt/meta.json", "gt/theta.npy", "gt/keypoints_3d.npy",
                "gt/keypoints_2d.npy", "gt/keypoints21_3d.npy", "gt/keypoints21_2d.npy"}
    for k in range(N):
        expected |= {f"depth/{frame_name(k)}", f"rgb/{frame_name(k)}", f"gt/ids/{frame_name(k)}"}
    assert names == expected
    info = read_sequence_info(seq)
    assert info.frames == N and info.models == ["hand_right"] and info.has_rgb
    assert info.source["noise"] == "none" and info.source["seed"] == 0
    gt = read_poses(seq / "gt")
    assert gt.theta.shape == (N, 37)
    assert gt.keypoints_3d.shape == (N, 1, 21, 3) and gt.keypoints_2d.shape == (N, 1, 21, 2)
    assert gt.keypoint_names[0] == "hand_right/wrist" and all(n.startswith("hand_right/") for n in gt.keypoint_names)
    assert len(gt.dof_names) == 37 and gt.valid.all()
    np.testing.assert_array_equal(read_init_pose(seq), gt.theta[0])


def test_ground_truth_theta_is_the_input(seq, frames):
    np.testing.assert_array_equal(read_poses(seq / "gt").theta, frames.theta.numpy())


def test_depth_matches_ids_and_a_fresh_render(seq, fresh):
    _, _, _, res = fresh
    for k in range(N):
        depth = read_depth(seq / "depth" / frame_name(k))
        ids = cv2.imread(str(seq / "gt" / "ids" / frame_name(k)), cv2.IMREAD_UNCHANGED)
        assert ids.dtype == np.uint8 and ids.shape == depth.shape == (480, 640)
        assert set(np.unique(ids).tolist()) <= {0, 1}
        hand = ids == 1
        assert hand.sum() > 500, "the hand should be visible"
        assert (depth[hand] > 0).all()
        assert (depth[~hand] == 0).all()  # no noise: nothing measured off the model
        np.testing.assert_array_equal(hand, res.model_id[k].numpy() == 0)
        ref = res.depth[k].numpy()
        assert np.abs(depth[hand] - ref[hand]).max() <= 1.0
        assert 300 < np.median(depth[hand]) < 1000


def test_rgb_is_the_shading_of_the_render(seq, fresh):
    _, _, _, res = fresh
    albedo = torch.tensor([[0.87, 0.67, 0.55]])
    shaded = shade_rgb(res, albedo).numpy()
    for k in range(N):
        rgb = read_rgb(seq / "rgb" / frame_name(k))
        ids = cv2.imread(str(seq / "gt" / "ids" / frame_name(k)), cv2.IMREAD_UNCHANGED)
        assert (rgb[ids == 0] == 64).all()  # grey background (0.25)
        diff = np.abs(rgb.astype(int) - shaded[k].astype(int))
        assert diff.max() <= 1
        skin = rgb[ids == 1].astype(int)
        assert (skin[:, 0] >= skin[:, 2]).all()  # skin: more red than blue


def test_keypoints_2d_are_the_projection_of_keypoints_3d(seq, fresh):
    info = read_sequence_info(seq)
    K = info.cameras[0].K.double().numpy()
    gt = read_poses(seq / "gt")
    X = gt.keypoints_3d[:, 0]
    assert (X[..., 2] > 0).all()
    u = K[0, 0] * X[..., 0] / X[..., 2] + K[0, 1] * X[..., 1] / X[..., 2] + K[0, 2]
    v = K[1, 1] * X[..., 1] / X[..., 2] + K[1, 2]
    np.testing.assert_allclose(gt.keypoints_2d[:, 0], np.stack([u, v], -1), atol=1e-6)
    # identity extrinsics: camera-frame keypoints are the posed (world) keypoints
    _, _, posed, _ = fresh
    np.testing.assert_allclose(X, posed.keypoints.numpy(), atol=1e-9)


def test_standard_joints_are_written_beside_the_keypoints(seq, fresh):
    from torchhand.data.layout import read_joints21
    from torchhand.model.joints21 import scene_standard_joints
    from torchhand.scoring.sequences import evaluate_sequence

    scene, cam, posed, _ = fresh
    j3, j2 = read_joints21(seq / "gt")
    assert j3.shape == (N, 1, 21, 3) and j2.shape == (N, 1, 21, 2)
    expected = cam.to_camera(scene_standard_joints(scene, posed)).numpy()
    np.testing.assert_allclose(j3[:, 0], expected, atol=1e-3)
    np.testing.assert_allclose(j2[:, 0], cam.project(torch.as_tensor(j3[:, 0])).numpy(), atol=1e-3)
    # the 21 joints share the model's joint centres (knuckles) with its own keypoints
    gt = read_poses(seq / "gt")
    knuckles = [i for i in range(1, 21) if i % 4]
    np.testing.assert_allclose(j3[:, :, knuckles], gt.keypoints_3d[:, :, knuckles], atol=1e-3)
    scores = evaluate_sequence(seq / "gt", seq / "gt", with_penetration=False)["joints21"]
    for key in ("mpjpe_mm", "pa_mpjpe_mm", "rr_mpjpe_mm", "mean_px"):
        assert scores[key] == pytest.approx(0.0, abs=1e-6), key
    assert scores["auc_0_50"] == 1.0 and scores["per_camera_px"] == [0.0]
    assert list(scores["per_joint"])[:2] == ["wrist", "thumb_cmc"]


def test_kinect_noise_is_seeded(frames, seq, tmp_path):
    one = _one(frames)
    paths = {}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        out = write_synthetic_sequence(one, tmp_path / name, noise="kinect", seed=seed, rgb=False, progress=False)
        paths[name] = (out / "depth" / frame_name(0)).read_bytes()
    assert paths["a"] == paths["b"]
    assert paths["a"] != paths["c"]
    # noise changes the depth: differs from the clean render
    d_clean = read_depth(seq / "depth" / frame_name(0))  # the same pose without noise
    d_noisy = read_depth(tmp_path / "a" / "depth" / frame_name(0))
    assert not np.array_equal(d_clean, d_noisy)
    both = (d_clean > 0) & (d_noisy > 0)
    assert both.sum() > 100 and np.median(np.abs(d_clean[both] - d_noisy[both])) < 10  # noise, not garbage
    assert not (tmp_path / "a" / "rgb").exists()
    assert json.loads((tmp_path / "a" / "sequence.json").read_text())["has_rgb"] is False


def test_existing_non_empty_out_is_refused(frames, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "sentinel.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="busy"):
        write_synthetic_sequence(_one(frames), out, noise="none", progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["sentinel.txt"]
    assert (out / "sentinel.txt").read_text() == "keep me"


def test_force_replaces_stale_content(frames, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "sentinel.txt").write_text("stale")
    write_synthetic_sequence(_one(frames), out, noise="none", force=True, rgb=False, progress=False)
    assert not (out / "sentinel.txt").exists()
    assert (out / "depth" / frame_name(0)).is_file() and read_sequence_info(out).frames == 1


def test_empty_existing_out_is_fine(frames, seq, tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    assert write_synthetic_sequence(_one(frames), out, noise="none", rgb=False, progress=False) == out
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["frames"] == 1 and meta["models"] == ["hand_right"] and meta["depth_unit_mm"] == 1.0
    assert meta["has_rgb"] is False and meta["has_depth"] is True and meta["source"]["noise"] == "none"
    info = read_sequence_info(out)
    assert info.frames == 1 and [(c.width, c.height) for c in info.cameras] == [(640, 480)]
    assert torch.equal(info.cameras[0].K, read_sequence_info(seq).cameras[0].K)
    # the first frame of the three-frame sequence, in millimetres
    depth = read_depth(out / "depth" / frame_name(0))
    assert depth.shape == (480, 640)
    np.testing.assert_array_equal(depth, read_depth(seq / "depth" / frame_name(0)))
    assert 300 < np.median(depth[depth > 0]) < 1000
    gt = read_poses(out / "gt")
    assert gt.theta.shape == (1, 37) and gt.keypoints_3d.shape == (1, 1, 21, 3)
    np.testing.assert_array_equal(gt.theta, frames.theta[:1].numpy())
    np.testing.assert_array_equal(read_init_pose(out), gt.theta[0])


def test_unknown_noise_is_rejected_before_writing(frames, tmp_path):
    out = tmp_path / "new"
    with pytest.raises(ValueError) as err:
        write_synthetic_sequence(_one(frames), out, noise="kinekt", progress=False)
    msg = str(err.value)
    assert "kinekt" in msg and "'none'" in msg and "'kinect'" in msg
    assert not out.exists()
    # also before --force would wipe an existing folder
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "sentinel.txt").write_text("keep me")
    with pytest.raises(ValueError, match="valid names"):
        write_synthetic_sequence(_one(frames), busy, noise="gaussian", force=True, progress=False)
    assert (busy / "sentinel.txt").read_text() == "keep me"


# ------------------------------------------------------------------ shading
def test_shade_rgb_lambert_ambient_and_background():
    light = torch.tensor([0.3, -0.4, -1.0])
    l = light / light.norm()
    perp = torch.linalg.cross(l, torch.tensor([1.0, 0.0, 0.0]))
    perp = perp / perp.norm()
    normals = torch.stack([l, perp, torch.zeros(3)])[None, None]  # (1, 1, 3, 3)
    model_id = torch.tensor([[[0, 1, -1]]])
    z = torch.zeros(1, 1, 3)
    res = RenderResult(depth=z, face_id=model_id, model_id=model_id, bone_id=model_id, normals=normals,
                       silhouette_edges=z.bool(), barycentric=torch.zeros(1, 1, 3, 2))
    albedo = torch.tensor([[1.0, 0.5, 0.0], [0.2, 0.4, 1.0]])
    out = shade_rgb(res, albedo, ambient=0.35)
    assert out.dtype == torch.uint8 and out.shape == (1, 1, 3, 3)
    assert out[0, 0, 0].tolist() == [255, 128, 0]  # fully lit: the albedo
    expect = (albedo[1] * 0.35 * 255).round().to(torch.uint8)
    assert (out[0, 0, 1].int() - expect.int()).abs().max() <= 1  # grazing light: ambient only
    assert out[0, 0, 2].tolist() == [64, 64, 64]  # background


# ------------------------------------------------------------------ thesis motions
@pytest.fixture(scope="module")
def motion16(hia_root):
    return thesis_motion(hia_root, "16", slice(0, 3))


@pytest.mark.slow
def test_thesis_motion_16(motion16):
    m = motion16
    assert m.scene.names == ["hand_right", "hand_left", "ball"]
    assert m.theta.shape == (3, 80) and m.scene.num_dofs == 80
    assert torch.isfinite(m.theta).all()
    assert len(m.cameras) == 1 and (m.cameras[0].width, m.cameras[0].height) == (640, 480)
    # the thesis calibration (Calibration/Cameras.txt): the Kinect intrinsics
    np.testing.assert_allclose(m.cameras[0].K.double().numpy(), [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])
    assert m.source["sequence"] == "16" and m.source["video_frames"][1] - m.source["video_frames"][0] == 2
    # consecutive frames of a motion are close (not random poses): < 20 mm, < 0.3 rad
    step = (m.theta[1:] - m.theta[:-1]).abs()
    trans = torch.tensor([n.split(":")[-1] in ("tx", "ty", "tz") for n in m.scene.dof_names])
    assert int(trans.sum()) == 9
    assert step[:, trans].max() < 20 and step[:, ~trans].max() < 0.3


@pytest.mark.slow
def test_thesis_sequence_written_with_its_camera(motion16, tmp_path):
    one = _one(motion16)
    out = write_synthetic_sequence(one, tmp_path / "hia", noise="none", rgb=False, progress=False)
    info = read_sequence_info(out)
    gt = read_poses(out / "gt")
    assert info.models == ["hand_right", "hand_left", "ball"] and gt.keypoints_3d.shape == (1, 1, 42, 3)
    cam = info.cameras[0].to(dtype=torch.float64)
    with torch.no_grad():
        world = one.scene(one.theta).keypoints
    # keypoints_3d are in the camera frame: T_cw applied
    np.testing.assert_allclose(gt.keypoints_3d[:, 0], cam.to_camera(world).numpy(), atol=1e-3)
    np.testing.assert_allclose(gt.keypoints_2d[:, 0], cam.project(world).numpy(), atol=1e-4)
    ids = cv2.imread(str(out / "gt" / "ids" / frame_name(0)), cv2.IMREAD_UNCHANGED)
    assert {1, 2} <= set(np.unique(ids).tolist())  # both hands seen by the thesis camera


@pytest.mark.parametrize("sequence", ["05"])
def test_thesis_sequence_without_motion_raises(hia_root, sequence):
    from torchhand.io.thesis import FormatError

    with pytest.raises(FormatError) as err:
        thesis_motion(hia_root, sequence, slice(0, 2))
    assert "MOTION" in str(err.value) and sequence in str(err.value)


def test_thesis_motion_empty_frame_range(hia_root):
    with pytest.raises(ValueError, match="no frame"):
        thesis_motion(hia_root, "16", slice(5, 5))
