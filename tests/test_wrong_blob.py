"""A track laid on the wrong blob: a model fitted to the body behind the hand is flagged by
the fit check on every frame it stays there, while the track of the hand is not."""

import json

import numpy as np
import pytest
import torch

from torchhand.app.runner import TrackOptions, track_sequences
from torchhand.data.layout import camera_dir, frame_name, read_depth, read_poses, write_depth
from torchhand.data.synth import SyntheticFrames, demo_motion, write_synthetic_sequence
from torchhand.model.scene import Scene

pytestmark = pytest.mark.slow

FRAMES = 6
BODY_BEHIND_MM = 160.0


def _hand_before_a_body(root):
    """The demo's right hand, clean depth, before a body: a surface 160 mm behind it
    filling the rest of the image (a torso seen close). Returns (sequence, truth)."""
    demo = demo_motion(slice(0, FRAMES))
    theta = demo.theta[:, demo.scene.slices["hand_right"]].clone()
    frames = SyntheticFrames(Scene.from_names(["hand_right"]), theta, demo.cameras, "body", {"format": "test"})
    seq = write_synthetic_sequence(frames, root, noise="none", rgb=False, progress=False)
    for f in range(FRAMES):
        path = camera_dir(seq, 0) / "depth" / frame_name(f)
        hand = read_depth(path)
        body = float(np.median(hand[hand > 0])) + BODY_BEHIND_MM
        write_depth(path, np.where(hand > 0, hand, body))
    return seq, read_poses(seq / "gt")


def _track(seq, out, start, reinit_iou: float = 0.0) -> tuple:
    (seq / "init_pose.json").write_text(json.dumps({"theta": [float(x) for x in start]}))
    [summary] = track_sequences([seq], out, TrackOptions(reinit_iou=reinit_iou), progress=False)
    log = json.loads((out / "body" / "track_log.json").read_text())["frames"]
    return summary, log, read_poses(out / "body")


def test_a_track_on_the_body_is_flagged_on_every_frame_it_stays_there(tmp_path):
    torch.manual_seed(0)
    seq, gt = _hand_before_a_body(tmp_path / "seq")
    # tracked from the truth: the hand ends in depth edges, no frame is flagged
    summary, log, pred = _track(seq, tmp_path / "hand", gt.theta[0])
    err = np.linalg.norm(pred.keypoints_3d - gt.keypoints_3d, axis=-1).mean((1, 2))
    assert err.max() < 6.0 and summary["fit_flagged_frames"] == 0
    assert max(r["surrounded"] for r in log) < 0.3
    # started on the body, beside the hand and as far back as the body: the model lies on it
    start = np.array(gt.theta[0], np.float64)
    cam = demo_motion(slice(0, 1)).cameras[0]
    start[:3] += (cam.T_wc[:3, :3].double() @ torch.tensor([140.0, 0.0, BODY_BEHIND_MM], dtype=torch.float64)).numpy()
    summary, log, pred = _track(seq, tmp_path / "body", start)
    err = np.linalg.norm(pred.keypoints_3d - gt.keypoints_3d, axis=-1).mean((1, 2))
    away = err > 50.0
    assert away[0], err  # the set-up: the track does stay on the body
    assert all(log[f]["fit_flagged"] and log[f]["surrounded"] > 0.6 for f in np.flatnonzero(away)), \
        [(r["surrounded"], r["iou"]) for r in log]
    assert summary["fit_flagged_frames"] >= int(away.sum())
    # with re-initialisation (the default): the flag starts a search, which segments the
    # frame automatically and finds the hand; the pose kept passes the check
    summary, log, pred = _track(seq, tmp_path / "refit", start, reinit_iou=0.5)
    err = np.linalg.norm(pred.keypoints_3d - gt.keypoints_3d, axis=-1).mean((1, 2))
    assert log[0]["fit_flagged"]  # frame 0 is not searched again
    back = [r["frame"] for r in log if r["reinitialized"]]
    assert back and back[0] == 1 and "surround is measured surface" in log[1]["notes"], log[1]["notes"]
    assert err[1:].max() < 10.0 and not any(r["fit_flagged"] for r in log[1:]), (err, log[1]["notes"])
