"""Re-initialisation: a hand that leaves the view and comes back elsewhere is found again."""

import json

import cv2
import numpy as np
import pytest
import torch

from torchhand.app.runner import TrackOptions, track_sequences
from torchhand.data.layout import camera_dir, frame_name, read_poses
from torchhand.data.synth import SyntheticFrames, demo_motion, write_synthetic_sequence
from torchhand.model.scene import Scene

# a 32-frame sequence tracked twice end to end
pytestmark = pytest.mark.slow


def _gap_sequence(root):
    """32 frames of the demo's right hand; frames 10-19 blanked (out of view), after which
    the hand is back 134 mm away and turned by 0.5 rad."""
    demo = demo_motion(slice(0, 32))
    theta = demo.theta[:, demo.scene.slices["hand_right"]].clone()
    theta[10:, 0] += 120.0
    theta[10:, 1] -= 60.0
    theta[10:, 5] += 0.5
    frames = SyntheticFrames(Scene.from_names(["hand_right"]), theta, demo.cameras, "gap", {"format": "test"})
    seq = write_synthetic_sequence(frames, root, noise="kinect", rgb=False, progress=False)
    for f in range(10, 20):
        cv2.imwrite(str(camera_dir(seq, 0) / "depth" / frame_name(f)), np.zeros((480, 640), np.uint16))
    gt = read_poses(seq / "gt")
    (seq / "init_pose.json").write_text(json.dumps({"theta": [float(x) for x in gt.theta[0]]}))
    return seq, gt


def test_a_hand_back_in_view_is_reinitialised_within_five_frames(tmp_path):
    torch.manual_seed(0)
    seq, gt = _gap_sequence(tmp_path / "seq")
    [summary] = track_sequences([seq], tmp_path / "out", progress=False)
    assert summary["status"] == "ok" and summary["flagged_frames"] == 10
    pred = read_poses(tmp_path / "out" / "gap")
    err = np.linalg.norm(pred.keypoints_3d - gt.keypoints_3d, axis=-1).mean((1, 2))
    assert err[:10].max() < 6.0
    assert err[20:25].min() < 6.0, err[20:25]  # back within 6 mm no later than 5 frames after
    assert err[25:].max() < 6.0, err[25:]
    log = json.loads((tmp_path / "out" / "gap" / "track_log.json").read_text())["frames"]
    flagged = [r["frame"] for r in log if r["reinitialized"]]
    assert flagged and 20 <= flagged[0] <= 24 and summary["reinitialized_frames"] == len(flagged)
    assert "re-initialised" in log[flagged[0]]["notes"]
    assert all(log[f]["iou"] is None and "no valid depth" in log[f]["notes"] for f in range(10, 20))
    # without it, the tracker starts the first frame back from the stale pose and is off
    # there: the test measures the re-initialisation. (Whether local search alone finds
    # the hand again some frames later depends on package versions: with some it does by
    # frame 26, so only the first frame back is compared.)
    [off] = track_sequences([seq], tmp_path / "off", TrackOptions(reinit_iou=0.0), progress=False)
    err_off = np.linalg.norm(read_poses(tmp_path / "off" / "gap").keypoints_3d - gt.keypoints_3d, axis=-1).mean((1, 2))
    assert off["reinitialized_frames"] == 0 and err_off[flagged[0]] > 10.0 and err[flagged[0]] < 6.0
