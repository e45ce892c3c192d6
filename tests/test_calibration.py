"""Hand-size calibration: the resized model, its exact posing, and a known size recovered."""

import json

import numpy as np
import pytest
import torch

import torchhand
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.shape import FINGERS, bone_scales, pose_resized, resize_hand


def test_resize_is_exact_and_poses_like_the_resized_model():
    model = torchhand.load_model("hand_right", dtype=torch.float64)
    a = model.assets
    same = resize_hand(a)
    assert np.abs(same.vertices - a.vertices).max() < 1e-9 and np.abs(same.rest_transforms - a.rest_transforms).max() < 1e-9
    big = resize_hand(a, 1.1, {"index": 1.2, "thumb": 0.9}, name="big")
    k = list(a.keypoint_names)
    length = lambda x, p, q: np.linalg.norm(x.keypoint_rest[k.index(p)] - x.keypoint_rest[k.index(q)])  # noqa: E731
    assert length(big, "index_tip", "index_mcp") / length(a, "index_tip", "index_mcp") == pytest.approx(1.32)
    assert length(big, "middle_mcp", "wrist") / length(a, "middle_mcp", "wrist") == pytest.approx(1.1)
    assert length(big, "thumb_tip", "thumb_mcp") / length(a, "thumb_tip", "thumb_mcp") == pytest.approx(0.99)
    resized = ArticulatedModel(big, dtype=torch.float64)
    theta = model.clamp(torch.randn(3, model.num_dofs, generator=torch.Generator().manual_seed(0),
                                    dtype=torch.float64) * 0.3)
    s = bone_scales(model, torch.full((3,), 1.1, dtype=torch.float64),
                    torch.tensor([[0.9, 1.2, 1.0, 1.0, 1.0]] * 3, dtype=torch.float64))
    verts, keypoints, _ = pose_resized(model, model(theta).G, s)
    out = resized(theta)
    assert (verts - out.vertices).abs().max() < 1e-9 and (keypoints - out.keypoints).abs().max() < 1e-9
    with pytest.raises(ValueError, match="unknown fingers"):
        resize_hand(a, fingers={"pinky": 1.1})
    with pytest.raises(ValueError, match="scale"):
        resize_hand(a, 0.0)


def test_calibrate_hand_on_one_rendered_frame():
    """The default tier's calibration: one clean frame of the shipped hand at its true
    pose, one short round; and its bad input."""
    from torchhand.data.synth import demo_motion
    from torchhand.geometry.render import render
    from torchhand.model.scene import Scene
    from torchhand.tracking.calibration import CalibrationConfig, calibrate_hand
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    demo = demo_motion(slice(0, 1), dtype=torch.float64)
    scene = Scene.from_names(["hand_right"], dtype=torch.float64)
    theta = demo.theta[:, demo.scene.slices["hand_right"]]
    cam = demo.cameras[0].to(dtype=torch.float64)
    with torch.no_grad():
        posed = scene(theta)
    depth = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id).depth[0]
    depth = depth.float().numpy()
    tracker = Tracker(scene, TrackerConfig(max_iterations=2, first_frame_iterations=2))
    cfg = CalibrationConfig(rounds=1, particles=4, generations=2, resolution=48, iterations=2)
    res = calibrate_hand(tracker, [depth], [cam], theta, cfg, name="mine")
    assert res.assets.name == "mine" and set(res.fingers) == set(FINGERS)
    assert res.theta.shape == (1, 37) and res.before.shape == res.after.shape == (1,)
    assert res.before[0] == pytest.approx(0.0, abs=1e-6)  # the frame is this hand's render at this pose
    # the start is one of the particles: the true size is kept, and the pose stays on the data
    assert res.scale == pytest.approx(1.0, abs=0.05) and all(0.85 <= f <= 1.18 for f in res.fingers.values())
    assert res.after[0] < 1.0
    with pytest.raises(ValueError, match="one camera and one pose per frame"):
        calibrate_hand(tracker, [depth, depth], [cam], theta, cfg)
    with pytest.raises(ValueError, match="calibration fits one hand"):
        calibrate_hand(Tracker(demo.scene), [depth], [cam], demo.theta, cfg)
    with pytest.raises(ValueError, match="CalibrationConfig.rounds must be an integer >= 1"):
        CalibrationConfig(rounds=0)


@pytest.mark.slow
def test_calibrate_recovers_the_size_of_a_larger_hand(tmp_path):
    from torchhand.app.cli import main
    from torchhand.data.synth import SyntheticFrames, demo_motion, write_synthetic_sequence
    from torchhand.io.assets import save_assets
    from torchhand.model.scene import Scene

    base = torchhand.load_model("hand_right").assets
    truth = resize_hand(base, 1.08, {"index": 1.06, "little": 0.94}, name="bigger")
    save_assets(truth, tmp_path / "bigger.npz")
    demo = demo_motion(slice(0, 40, 10))
    theta = demo.theta[:, demo.scene.slices["hand_right"]]
    scene = Scene([ArticulatedModel(truth)], names=["hand_right"])
    seq = write_synthetic_sequence(SyntheticFrames(scene, theta, demo.cameras, "big", {"format": "test"}),
                                   tmp_path / "seq", noise="kinect", rgb=False, progress=False)
    out = tmp_path / "my_hand.npz"
    assert main(["calibrate", str(seq), "--model", "hand_right", "--out", str(out), "--frames", "4"]) == 0
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["scale"] == pytest.approx(1.08, abs=0.04)  # measured: 1.055 (docs/real.md)
    assert rep["mean_iou_after"] >= rep["mean_iou_before"]
    assert set(rep["fingers"]) == set(FINGERS) and len(rep["frames"]) == 4
    assert main(["calibrate", str(seq), "--out", str(out)]) == 2  # nothing is overwritten
    # the model is accepted by --models
    assert main(["track", str(seq), "--out", str(tmp_path / "track"), "--models", str(out)]) == 0
    log = json.loads((tmp_path / "track" / "big" / "track_log.json").read_text())
    assert np.mean([f["iou"] for f in log["frames"]]) > 0.85


def test_eval_without_ground_truth_reports_the_fit(tmp_path, capsys):
    from torchhand.app.cli import main

    d = tmp_path / "pred"
    d.mkdir()
    frames = [{"frame": 0, "iou": 0.9, "depth_residual_mm": 1.0, "valid": True, "reinitialized": False},
              {"frame": 1, "iou": 0.6, "depth_residual_mm": 3.0, "valid": True, "reinitialized": True},
              {"frame": 2, "iou": None, "depth_residual_mm": None, "valid": False, "reinitialized": False}]
    (d / "track_log.json").write_text(json.dumps({"sequence": "s", "frames": frames}))
    assert main(["eval", str(d), "--json", str(tmp_path / "fit.json")]) == 0
    res = json.loads((tmp_path / "fit.json").read_text())
    assert res["mean_iou"] == pytest.approx(0.75) and res["min_iou"] == pytest.approx(0.6)
    assert res["frames_below_iou"] == 1 and res["median_depth_residual_mm"] == pytest.approx(2.0)
    [s] = res["sequences"]
    assert s["worst_frame"] == 1 and s["reinitialized_frames"] == 1 and s["flagged_frames"] == 1
    assert "silhouette IoU mean 0.75" in capsys.readouterr().out
    assert main(["eval", str(tmp_path)]) == 2  # no track log: a clear error
