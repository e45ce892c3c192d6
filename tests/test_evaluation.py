"""Scoring predictions against ground truth: exact values for known offsets, PCK/AUC,
errors for incomparable folders, parallel evaluation and interpenetration."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.data.layout import Poses, read_poses, write_poses
from torchhand.app.scaleout import evaluate_pairs
from torchhand.scoring.sequences import JOINT_KEYS, EvaluationError, evaluate_many, evaluate_sequence
from torchhand.scoring.metrics import PCK_THRESHOLDS_MM, auc, keypoint_errors, pck_curve, penetration
from torchhand.model.scene import Scene

FX = 525.0


def _project(kp3d):
    """(..., 3) camera-frame mm -> (..., 2) px of the Kinect camera."""
    return np.stack([FX * kp3d[..., 0] / kp3d[..., 2] + 319.5, FX * kp3d[..., 1] / kp3d[..., 2] + 239.5], -1)


def _gt_poses(models, N, seed=0):
    """Ground truth for random in-limit poses: keypoints rounded to 1/64 mm so that
    shifting them by whole millimetres is exact in floating point."""
    scene = Scene.from_names(models, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    lo, hi = scene.lower.clone(), scene.upper.clone()
    fin = torch.isfinite(lo) & torch.isfinite(hi)
    theta = torch.where(fin, lo.nan_to_num(0) + torch.rand(N, scene.num_dofs, generator=g, dtype=torch.float64)
                        * (hi - lo).nan_to_num(0), torch.zeros(N, scene.num_dofs, dtype=torch.float64))
    for k, name in enumerate(scene.names):
        s = scene.slices[name]
        theta[:, s.start + 2] = 600.0  # in front of the camera
        theta[:, s.start] = 200.0 * k
    with torch.no_grad():
        world = scene(theta).keypoints
    cam = kinect_camera(dtype=torch.float64)
    kp3d = np.round(cam.to_camera(world).numpy()[:, None] * 64) / 64  # (N, 1, P, 3)
    assert (kp3d[..., 2] > 100).all()
    return Poses(theta.numpy(), kp3d, _project(kp3d), list(scene.names), scene.dof_names, scene.keypoint_names)


def _shifted(p: Poses, mm=(5.0, 0.0, 0.0)) -> Poses:
    kp3d = p.keypoints_3d + np.asarray(mm)
    return Poses(p.theta.copy(), kp3d, _project(kp3d), p.models, p.dof_names, p.keypoint_names)


@pytest.fixture(scope="module")
def gt1():
    return _gt_poses(["hand_right"], 3)


@pytest.fixture
def gt_dir(gt1, tmp_path):
    d = tmp_path / "seq" / "gt"
    write_poses(d, gt1)
    return d


# ------------------------------------------------------------------ metrics
def test_pck_and_auc_basics():
    t = PCK_THRESHOLDS_MM
    assert len(t) == 51 and t[0] == 0 and t[-1] == 50 and np.all(np.diff(t) == 1)
    np.testing.assert_array_equal(pck_curve(np.zeros(7)), np.ones(51))
    assert auc(t, np.ones(51)) == 1.0 and auc(t, np.zeros(51)) == 0.0
    c = pck_curve(np.array([0.5, 2.0, 2.0, 100.0]))
    assert c[0] == 0 and c[1] == 0.25 and c[2] == 0.75 and c[50] == 0.75
    np.testing.assert_array_equal(pck_curve(np.array([])), np.zeros(51))
    e = keypoint_errors(np.array([[[3.0, 4.0]]]), np.zeros((1, 1, 2)))
    assert e.shape == (1, 1) and e[0, 0] == 5.0


# ------------------------------------------------------------------ exact scores
def test_ground_truth_against_itself_scores_zero(gt_dir):
    r = evaluate_sequence(gt_dir, gt_dir)
    assert r["frames"] == 3
    assert r["thesis_mean_px"] == 0.0 and r["median_px"] == 0.0
    assert r["mean_mm"] == 0.0 and r["median_mm"] == 0.0
    assert r["auc_0_50mm"] == 1.0
    assert r["pck"]["fraction"] == [1.0] * 51
    assert r["flagged_frames"] == 0 and "penetration" not in r  # one model: nothing to penetrate
    assert r["sequence"] == "seq"
    assert set(r["per_keypoint"]) == set(read_poses(gt_dir).keypoint_names)
    assert r["per_frame"]["mm"] == [0.0] * 3
    json.dumps(r)  # JSON-ready
    # a sequence folder holding gt/ is accepted on either side
    r2 = evaluate_sequence(gt_dir.parent, gt_dir.parent)
    assert r2["mean_mm"] == 0.0 and r2["frames"] == 3


def test_shift_of_5mm(gt1, gt_dir, tmp_path):
    pred = _shifted(gt1)
    write_poses(tmp_path / "pred", pred)
    r = evaluate_sequence(tmp_path / "pred", gt_dir)
    assert abs(r["mean_mm"] - 5.0) <= 1e-9 and abs(r["median_mm"] - 5.0) <= 1e-9
    # a 5 mm shift along x moves u by fx * 5 / z pixels, v not at all
    expect_px = FX * 5.0 / gt1.keypoints_3d[..., 2]
    assert abs(r["thesis_mean_px"] - expect_px.mean()) <= 1e-9
    assert abs(r["median_px"] - np.median(expect_px)) <= 1e-9
    curve = np.asarray(r["pck"]["fraction"])
    np.testing.assert_array_equal(r["pck"]["thresholds_mm"], np.arange(51.0))
    np.testing.assert_array_equal(curve[:5], 0.0)  # 0..4 mm: none within
    np.testing.assert_array_equal(curve[5:], 1.0)  # 5..50 mm: all within
    # trapezoid over 0..50 mm: 0.5 for [4, 5] plus 45 unit intervals, over 50 mm
    assert abs(r["auc_0_50mm"] - 45.5 / 50) <= 1e-12
    np.testing.assert_allclose(r["per_frame"]["mm"], 5.0, atol=1e-9)
    assert all(abs(v["mm"] - 5.0) <= 1e-9 for v in r["per_keypoint"].values())


def test_shift_of_3_4_0_is_5mm_too(gt1, gt_dir, tmp_path):
    write_poses(tmp_path / "pred", _shifted(gt1, (3.0, -4.0, 0.0)))
    r = evaluate_sequence(tmp_path / "pred", gt_dir)
    assert abs(r["mean_mm"] - 5.0) <= 1e-9 and abs(r["auc_0_50mm"] - 0.91) <= 1e-12


def test_flagged_frames_are_counted(gt1, gt_dir, tmp_path):
    p = _shifted(gt1, (0.0, 0.0, 0.0))
    p.valid = np.array([True, False, False])
    write_poses(tmp_path / "pred", p)
    assert evaluate_sequence(tmp_path / "pred", gt_dir)["flagged_frames"] == 2


# ------------------------------------------------------------------ incomparable folders
def test_frame_count_mismatch(gt1, gt_dir, tmp_path):
    p = Poses(gt1.theta[:2], gt1.keypoints_3d[:2], gt1.keypoints_2d[:2], gt1.models, gt1.dof_names,
              gt1.keypoint_names)
    write_poses(tmp_path / "pred", p)
    with pytest.raises(EvaluationError, match="2 frames.*3"):
        evaluate_sequence(tmp_path / "pred", gt_dir)


def test_nan_in_prediction_names_file_and_frame(gt1, gt_dir, tmp_path):
    kp3d = gt1.keypoints_3d.copy()
    kp3d[1, 0, 4, 2] = np.nan
    write_poses(tmp_path / "pred", Poses(gt1.theta, kp3d, gt1.keypoints_2d, gt1.models, gt1.dof_names,
                                          gt1.keypoint_names))
    with pytest.raises(EvaluationError) as err:
        evaluate_sequence(tmp_path / "pred", gt_dir)
    msg = str(err.value)
    assert str(tmp_path / "pred" / "keypoints_3d.npy") in msg
    assert "[1]" in msg


def test_inf_in_theta_names_theta(gt1, gt_dir, tmp_path):
    theta = gt1.theta.copy()
    theta[2, 7] = np.inf
    write_poses(tmp_path / "pred", Poses(theta, gt1.keypoints_3d, gt1.keypoints_2d, gt1.models, gt1.dof_names,
                                          gt1.keypoint_names))
    with pytest.raises(EvaluationError, match=r"theta\.npy.*\[2\]"):
        evaluate_sequence(tmp_path / "pred", gt_dir)


def test_different_keypoint_names(gt1, gt_dir, tmp_path):
    names = list(gt1.keypoint_names)
    names[3] = "hand_right/something_else"
    write_poses(tmp_path / "pred", Poses(gt1.theta, gt1.keypoints_3d, gt1.keypoints_2d, gt1.models, gt1.dof_names,
                                          names))
    with pytest.raises(EvaluationError, match="keypoint names"):
        evaluate_sequence(tmp_path / "pred", gt_dir)


def test_different_camera_count(gt1, gt_dir, tmp_path):
    two = lambda a: np.concatenate([a, a], 1)  # noqa: E731
    write_poses(tmp_path / "pred", Poses(gt1.theta, two(gt1.keypoints_3d), two(gt1.keypoints_2d), gt1.models,
                                          gt1.dof_names, gt1.keypoint_names))
    with pytest.raises(EvaluationError):
        evaluate_sequence(tmp_path / "pred", gt_dir)


def test_missing_prediction_folder(gt_dir, tmp_path):
    with pytest.raises(EvaluationError, match="nothing"):
        evaluate_sequence(tmp_path / "nothing", gt_dir)


# ------------------------------------------------------------------ many sequences
@pytest.mark.slow
def test_evaluate_many_parallel_equals_serial(gt1, tmp_path):
    pairs = []
    for k, shift in enumerate([(1.0, 0, 0), (0, 7.0, 0), (0, 0, 20.0)]):
        write_poses(tmp_path / f"s{k}" / "gt", gt1)
        write_poses(tmp_path / f"p{k}", _shifted(gt1, shift))
        pairs.append((tmp_path / f"p{k}", tmp_path / f"s{k}"))
    serial = evaluate_many(pairs, progress=False)
    parallel = evaluate_pairs(pairs, workers=2, progress=False)
    assert parallel.pop("failed") == []
    for s in parallel["sequences"]:  # the pairs go to the workers as absolute paths
        s["prediction"] = str(Path(s["prediction"]).relative_to(tmp_path.resolve()))
    for s in serial["sequences"]:
        s["prediction"] = str(Path(s["prediction"]).relative_to(tmp_path))
    assert serial == parallel
    assert serial["frames"] == 9 and len(serial["sequences"]) == 3
    assert [s["sequence"] for s in serial["sequences"]] == ["s0", "s1", "s2"]
    assert abs(serial["mean_mm"] - (1 + 7 + 20) / 3) <= 1e-9
    one = evaluate_many(pairs[:1], progress=False)
    assert "sequences" not in one and abs(one["mean_mm"] - 1.0) <= 1e-9


def test_evaluate_many_pools_all_keypoints(gt1, tmp_path):
    gt2 = _gt_poses(["hand_right", "hand_left"], 3, seed=1)  # 42 keypoints per frame
    write_poses(tmp_path / "a" / "gt", gt1)
    write_poses(tmp_path / "pa", _shifted(gt1, (5.0, 0, 0)))
    write_poses(tmp_path / "b" / "gt", gt2)
    write_poses(tmp_path / "pb", _shifted(gt2, (10.0, 0, 0)))
    r = evaluate_many([(tmp_path / "pa", tmp_path / "a"), (tmp_path / "pb", tmp_path / "b")],
                      with_penetration=False, progress=False)
    # 3 * 21 keypoints 5 mm off, 3 * 42 keypoints 10 mm off
    assert abs(r["mean_mm"] - (63 * 5 + 126 * 10) / 189) <= 1e-9


# ------------------------------------------------------------------ interpenetration
def _two_hands(offset_mm):
    """theta (1, 74) of hand_right at rest and hand_left with its root joint at hand_right's
    root, moved by offset_mm along x."""
    scene = Scene.from_names(["hand_right", "hand_left"], dtype=torch.float64)
    theta = scene.zero_pose(1).double()
    sr, sl = scene.slices["hand_right"], scene.slices["hand_left"]
    theta[0, sr.start + 2] = 600.0
    root_r = scene.models[0].rest_transforms[0, :3, 3]
    root_l = scene.models[1].rest_transforms[0, :3, 3]
    theta[0, sl.start:sl.start + 3] = theta[0, sr.start:sr.start + 3] + root_r - root_l
    theta[0, sl.start] += offset_mm
    return scene, theta


def _write_two_hand_pair(tmp_path, name, offset_mm):
    scene, theta = _two_hands(offset_mm)
    P = len(scene.keypoint_names)
    kp3d = np.zeros((1, 1, P, 3))
    kp3d[..., 2] = 600.0
    p = Poses(theta.numpy(), kp3d, _project(kp3d), list(scene.names), scene.dof_names, scene.keypoint_names)
    write_poses(tmp_path / name, p)
    return tmp_path / name


@pytest.mark.slow
def test_penetration_of_overlapping_and_separate_hands(tmp_path):
    inside = _write_two_hand_pair(tmp_path, "inside", 0.0)
    r = evaluate_sequence(inside, inside)
    assert r["mean_mm"] == 0.0
    pen = r["penetration"]
    assert pen["pairs_per_frame"] > 0 and pen["max_pairs"] > 0 and pen["max_depth_mm"] > 0
    apart = _write_two_hand_pair(tmp_path, "apart", 300.0)
    pen = evaluate_sequence(apart, apart)["penetration"]
    assert pen == {"pairs_per_frame": 0.0, "max_pairs": 0, "max_depth_mm": 0.0}
    # switched off on request
    assert "penetration" not in evaluate_sequence(apart, apart, with_penetration=False)


@pytest.mark.slow
def test_penetration_metric_on_meshes():
    scene, theta = _two_hands(300.0)
    with torch.no_grad():
        out = scene(theta)
    faces = [m.faces.numpy() for m in scene.models]
    apart = penetration([(o.vertices[0].numpy(), f) for o, f in zip(out.models, faces)])
    assert apart.max_depth_mm == 0.0 and apart.pairs == 0
    # the same mesh twice, one copy shifted by 3 mm into itself: vertices inside, faces crossing
    v, f = out.models[0].vertices[0].numpy(), faces[0]
    pen = penetration([(v, f), (v + np.array([3.0, 0.0, 0.0]), f)])
    assert pen.max_depth_mm > 0.5
    assert pen.pairs > 0


@pytest.mark.slow
def test_max_depth_sign_does_not_flip_on_a_grazing_ray(hia_root):
    """Frame 71 of thesis sequence 03 (float32 pose, as rendered): with one ray for the
    inside test, a vertex of one hand 19 mm outside the other was counted 19 mm deep
    (a grazing ray); the true deepest vertex is 1.5 mm."""
    from torchhand.data.synth import thesis_motion
    from torchhand.scoring.metrics import max_depth

    fr = thesis_motion(hia_root, "03", slice(44, 84), dtype=torch.float32)
    scene = Scene.from_names(fr.scene.names, dtype=torch.float64)
    with torch.no_grad():
        out = scene(fr.theta[27:28].double())
    depth = max_depth([(o.vertices[0].numpy(), m.faces.numpy()) for o, m in zip(out.models, scene.models)])
    assert 1.0 < depth < 2.0, depth


# ------------------------------------------------------------------ every model scored
@pytest.fixture(scope="module")
def hand_objects():
    return _gt_poses(["hand_right", "ball", "cube", "rope"], 3, seed=2)


def _moved(p: Poses, model: str, dofs: dict) -> Poses:
    """p with the root DoFs of one model changed (``{"root:tx": 5.0}``), keypoints kept."""
    theta = p.theta.copy()
    for dof, delta in dofs.items():
        theta[:, p.dof_names.index(f"{model}/{dof}")] += delta
    return Poses(theta, p.keypoints_3d.copy(), p.keypoints_2d.copy(), p.models, p.dof_names, p.keypoint_names)


def test_every_model_scored_zero_against_itself(hand_objects, tmp_path):
    write_poses(tmp_path / "gt", hand_objects)
    r = evaluate_sequence(tmp_path / "gt", tmp_path / "gt", with_penetration=False)
    assert set(r["models"]) == {"hand_right", "ball", "cube", "rope"}
    assert {n: m["metric"] for n, m in r["models"].items()} == {
        "hand_right": "keypoints", "ball": "ADD-S (sphere)", "cube": "ADD-S (cube)", "rope": "bone origins"}
    for m in r["models"].values():
        assert m["mean_mm"] <= 1e-9 and m["worst_frame_mm"] <= 1e-9 and m["frames_over_20mm"] == 0
    assert r["lost_frames"] == 0


def test_a_known_shift_of_each_model_is_its_score(hand_objects, tmp_path):
    """A rigid shift of 5 mm is ADD 5 mm (ADD-S at most that), a rope shifted by 25 mm
    has its bone origins and vertices 25 mm off and every frame lost; the hand is untouched."""
    write_poses(tmp_path / "gt", hand_objects)
    pred = _moved(_moved(_moved(hand_objects, "ball", {"root:tx": 5.0}), "cube", {"root:ty": -5.0}),
                  "rope", {"root:tz": 25.0})
    write_poses(tmp_path / "pred", pred)
    r = evaluate_sequence(tmp_path / "pred", tmp_path / "gt", with_penetration=False)
    m = r["models"]
    assert m["hand_right"]["mean_mm"] <= 1e-9
    for name in ("ball", "cube"):
        assert abs(m[name]["add_mean_mm"] - 5.0) <= 1e-6
        assert 0.0 < m[name]["mean_mm"] <= 5.0 + 1e-6
    assert abs(m["rope"]["mean_mm"] - 25.0) <= 1e-6 and abs(m["rope"]["vertices_mean_mm"] - 25.0) <= 1e-6
    assert m["rope"]["frames_over_20mm"] == 3 and r["lost_frames"] == 3


def test_a_symmetric_pose_costs_nothing_under_add_s(tmp_path):
    """The cube turned by 90 degrees about one of its axes is the same shape: ADD-S near 0
    (the vertices differ by their sampling only), ADD large."""
    gt = _gt_poses(["cube"], 2, seed=3)
    gt.theta[:, 3:6] = 0.0  # axis-aligned, so that a quarter turn about z maps the cube onto itself
    write_poses(tmp_path / "gt", gt)
    scene = Scene.from_names(["cube"], dtype=torch.float64)
    turned = gt.theta.copy()
    turned[:, 5] = np.pi / 2
    with torch.no_grad():  # the root translation puts the turned cube's centre back
        centre = [scene(torch.as_tensor(t)).vertices.mean(1).numpy() for t in (gt.theta, turned)]
    turned[:, :3] += centre[0] - centre[1]
    write_poses(tmp_path / "pred", Poses(turned, gt.keypoints_3d, gt.keypoints_2d, gt.models, gt.dof_names,
                                          gt.keypoint_names))
    m = evaluate_sequence(tmp_path / "pred", tmp_path / "gt", with_penetration=False)["models"]["cube"]
    assert m["mean_mm"] < 1.0 and m["add_mean_mm"] > 10.0, m


# ------------------------------------------------------------------ the standard 21 joints
def _joints21(N=4, hands=1, seed=0):
    rng = np.random.default_rng(seed)
    j3 = rng.normal(0.0, 40.0, (N, 1, 21 * hands, 3)) + np.array([0.0, 0.0, 600.0])
    return j3, _project(j3)


def test_joints21_block_for_a_known_shift(gt1, gt_dir, tmp_path):
    from torchhand.data.layout import write_joints21

    j3, j2 = _joints21(N=len(gt1.theta))
    write_joints21(gt_dir, j3, j2)
    pred_dir = tmp_path / "pred"
    write_poses(pred_dir, gt1)
    shifted = j3 + np.array([3.0, 4.0, 0.0])
    write_joints21(pred_dir, shifted, _project(shifted))
    r = evaluate_sequence(pred_dir, gt_dir, with_penetration=False)
    same = evaluate_sequence(gt_dir, gt_dir, with_penetration=False)
    own = ("thesis_mean_px", "mean_mm", "median_px", "auc_0_50mm")
    assert {k: r[k] for k in own} == {k: same[k] for k in own}  # the thesis keypoints' own keys kept
    b = r["joints21"]
    assert {k: r[k] for k in JOINT_KEYS} == {k: b[k] for k in JOINT_KEYS}  # the 21 joints' at the top level
    assert b["mpjpe_mm"] == pytest.approx(5.0)
    assert b["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6) and b["rr_mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
    assert b["auc_0_50"] == pytest.approx(auc(PCK_THRESHOLDS_MM, pck_curve(np.full(10, 5.0))), abs=0.02)  # at 5 mm
    assert b["mean_px"] == pytest.approx(np.linalg.norm(_project(shifted) - j2, axis=-1).mean())
    assert set(b["per_joint"]) >= {"wrist", "thumb_tip", "little_tip"} and b["scored_joints"] == 21 * len(gt1.theta)
    for key in ("mpjpe_mm", "pa_mpjpe_mm", "rr_mpjpe_mm", "mean_px"):
        assert same["joints21"][key] == pytest.approx(0.0, abs=1e-6), key
    assert same["joints21"]["auc_0_50"] == 1.0


def test_joints21_a_dataset_lacks_are_left_out(gt1, gt_dir, tmp_path):
    from torchhand.data.layout import write_joints21

    j3, j2 = _joints21(N=len(gt1.theta))
    pred3 = j3.copy()
    pred3[0, 0, 5] += 100.0  # a joint the dataset lacks (all -1) ...
    pred3[1, 0, 6] += 100.0  # ... or has as NaN: the prediction there does not count
    gt3, gt2 = j3.copy(), j2.copy()
    gt3[0, 0, 5], gt2[0, 0, 5] = -1.0, -1.0
    gt3[1, 0, 6], gt2[1, 0, 6] = np.nan, np.nan
    write_joints21(gt_dir, gt3, gt2)
    pred_dir = tmp_path / "pred"
    write_poses(pred_dir, gt1)
    write_joints21(pred_dir, pred3, _project(pred3))
    b = evaluate_sequence(pred_dir, gt_dir, with_penetration=False)["joints21"]
    assert b["mpjpe_mm"] == 0.0 and b["mean_px"] == 0.0 and b["scored_joints"] == 21 * len(gt1.theta) - 2


def test_joints21_absent_on_one_side_adds_no_block(gt1, gt_dir, tmp_path):
    from torchhand.data.layout import write_joints21

    write_joints21(gt_dir, *_joints21(N=len(gt1.theta)))
    pred_dir = tmp_path / "pred"
    write_poses(pred_dir, gt1)  # an older output: no 21 joints
    assert "joints21" not in evaluate_sequence(pred_dir, gt_dir, with_penetration=False)


def test_joints21_pooled_over_sequences(gt1, tmp_path):
    from torchhand.data.layout import write_joints21

    pairs = []
    for k, (frames, mm) in enumerate(((3, 5.0), (3, 10.0))):
        gt_dir, pred_dir = tmp_path / f"s{k}" / "gt", tmp_path / f"p{k}"
        write_poses(gt_dir, gt1)
        write_poses(pred_dir, gt1)
        j3, j2 = _joints21(N=len(gt1.theta), hands=1, seed=k)
        write_joints21(gt_dir, j3, j2)
        write_joints21(pred_dir, j3 + np.array([mm, 0.0, 0.0]), _project(j3 + np.array([mm, 0.0, 0.0])))
        pairs.append((pred_dir, gt_dir))
    pooled = evaluate_many(pairs, with_penetration=False, progress=False)
    assert pooled["joints21"]["mpjpe_mm"] == pytest.approx(7.5)
    assert pooled["joints21"]["scored_joints"] == 2 * 21 * len(gt1.theta)


# ------------------------------------------------------------------ ground truth of 21 joints alone
def _joints_only(folder, j3, j2, valid=None):
    """A public dataset's gt/: the 21 joints (and a validity mask), no theta, no meta.json."""
    from torchhand.data.layout import write_joints21

    folder.mkdir(parents=True)
    write_joints21(folder, j3, j2, valid)
    return folder


def test_ground_truth_of_joints_alone(gt1, tmp_path):
    from torchhand.data.layout import write_joints21

    N = len(gt1.theta)
    j3, j2 = _joints21(N=N)
    valid = np.ones((N, 21), bool)
    valid[1] = False  # a frame without a hand pose: its joints (here garbage) are left out
    gt3 = j3.copy()
    gt3[1] = -1.0
    gt_dir = _joints_only(tmp_path / "seq" / "gt", gt3, j2, valid)
    pred_dir = tmp_path / "pred"
    write_poses(pred_dir, gt1)  # a tracker's output: its own poses and the 21 joints
    shifted = j3 + np.array([3.0, 4.0, 0.0])
    shifted[2, 0, :] += np.array([0.0, 0.0, 30.0])  # frame 2 off by ~30.4 mm: lost
    write_joints21(pred_dir, shifted, _project(shifted))
    r = evaluate_sequence(pred_dir, tmp_path / "seq", with_penetration=False)  # the sequence folder is accepted
    assert r["frames"] == N and r["ground_truth"] == "the standard 21 joints only" and r["sequence"] == "seq"
    assert set(JOINT_KEYS) <= set(r) and "thesis_mean_px" not in r and "models" not in r
    expect = np.r_[5.0, np.linalg.norm([3.0, 4.0, 30.0]), np.full(N - 3, 5.0)]
    assert r["mpjpe_mm"] == pytest.approx(expect.mean()) and r["joints21"]["scored_joints"] == 21 * (N - 1)
    assert np.isnan(r["joints21"]["per_frame_mm"][1]) and r["joints21"]["per_frame_mm"][0] == pytest.approx(5.0)
    assert r["lost_frames"] == 1 and r["lost_frame_ids"] == [2]
    px = np.linalg.norm(_project(shifted) - j2, axis=-1)[[0, *range(2, N)]]
    assert r["mean_px"] == pytest.approx(px.mean())  # the frame without a pose is left out of 2D too
    json.dumps(r)
    pooled = evaluate_many([(pred_dir, gt_dir), (pred_dir, gt_dir)], with_penetration=False, progress=False)
    assert pooled["mpjpe_mm"] == pytest.approx(r["mpjpe_mm"]) and pooled["lost_frames"] == 2
    assert "thesis_mean_px" not in pooled and pooled["frames"] == 2 * N


def test_joints_alone_need_the_predictions_joints(gt1, tmp_path):
    j3, j2 = _joints21(N=len(gt1.theta))
    gt_dir = _joints_only(tmp_path / "gt", j3, j2)
    write_poses(tmp_path / "old", gt1)  # no keypoints21
    with pytest.raises(EvaluationError, match="holds the standard 21 joints only, but .*old has none"):
        evaluate_sequence(tmp_path / "old", gt_dir)
    _joints_only(tmp_path / "short", j3[:-1], j2[:-1])
    with pytest.raises(EvaluationError, match=r"21-joint arrays of .*short \(2, 1, 21, 3\) do not match"):
        evaluate_sequence(tmp_path / "short", gt_dir)
