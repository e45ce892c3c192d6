"""The demo: pose the default scene through a short motion, render it, write overlays."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchhand.data.layout import OutputLayout, SequenceLayout
from torchhand.geometry.camera import kinect_camera
from torchhand.io.assets import load_demo_motion
from torchhand.geometry.render import render
from torchhand.model.scene import Scene
from torchhand.app.drawing import depth_range, depth_to_color, draw_colorbar, draw_legend, draw_skeleton, write_video
from torchhand.io.output_dir import prepare_output_dir

__all__ = ["run_demo"]


def run_demo(out: Path, frames: int | None = None, force: bool = False, device: str = "cpu",
             track_frames: int = 8) -> dict:
    """Render the default scene (two hands and a ball) through the demo motion, then
    synthesise the first ``track_frames`` frames with Kinect noise, track them from
    the first-frame pose and score the result.

    Writes ``overlays/NNNNNN.png`` (depth in false colour with projected skeletons),
    ``demo.mp4``, ``keypoints_2d.json``, ``sequence/`` (the synthetic input with its
    ground truth), ``track/`` (the tracker's output with overlays), ``eval.json`` and
    ``summary.json`` to ``out``.
    """
    out = prepare_output_dir(out, force)
    names, theta = load_demo_motion()
    theta = theta[:frames] if frames else theta
    scene = Scene.from_names(names, device=device)
    theta = theta.to(device)
    cam = kinect_camera().to(device)
    overlays = OutputLayout(out)  # the overlays as a tracker's output folder has them
    overlays.overlays_dir.mkdir()
    depths, kp2d, t_render = [], [], 0.0
    hands = [n for n, m in zip(scene.names, scene.models) if m.kind == "hand"]
    for k in tqdm(range(len(theta)), desc="demo", unit="frame"):
        with torch.no_grad():
            posed = scene(theta[k : k + 1])
        t0 = time.perf_counter()
        res = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
        t_render += time.perf_counter() - t0
        depths.append(res.depth[0].cpu().numpy())
        kp2d.append({n: cam.project(posed.models[scene.names.index(n)].keypoints)[0].cpu().numpy().round(2).tolist()
                     for n in hands})
    near, far = depth_range(depths)  # one colour scale for the whole motion
    images = []
    for k, depth in enumerate(depths):
        img = depth_to_color(depth, near, far)
        for n in hands:
            draw_skeleton(img, np.asarray(kp2d[k][n]))
        draw_colorbar(img, near, far)
        draw_legend(img, f"frame {k}", [(f"{n}: posed" if n in hands else f"{n} (depth only)", None)
                                        for n in scene.names])
        cv2.imwrite(str(overlays.overlay(k)), img)
        images.append(img)
    write_video(images, out / "demo.mp4")
    (out / "keypoints_2d.json").write_text(json.dumps(kp2d))
    tracking = _track_demo(out, scene, theta[:track_frames], cam, device) if track_frames > 0 else None
    summary = {
        "frames": len(theta),
        "models": names,
        "dofs": scene.num_dofs,
        "vertices": scene.num_vertices,
        "triangles": int(scene.faces.shape[0]),
        "image_size": [cam.width, cam.height],
        "render_ms_per_frame": 1000 * t_render / max(len(theta), 1),
        "tracking": tracking,
        "outputs": ["overlays/", "demo.mp4", "keypoints_2d.json"]
        + (["sequence/", "track/", "eval.json"] if tracking else []) + ["summary.json"],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _track_demo(out: Path, scene: Scene, theta: torch.Tensor, cam, device: str) -> dict:
    """Synthesise -> track -> evaluate a few frames; returns the headline scores."""
    from torchhand.data.synth import SyntheticFrames, write_synthetic_sequence
    from torchhand.scoring.sequences import evaluate_sequence
    from torchhand.app.options import TrackOptions
    from torchhand.app.runner import track_sequences
    from torchhand.tracking.tracker import TrackerConfig

    frames = SyntheticFrames(scene, theta, [cam], "demo", {"format": "demo motion"})
    seq = write_synthetic_sequence(frames, out / "sequence", noise="kinect", seed=0)
    cfg = TrackerConfig(metric="point-to-plane", max_iterations=10, first_frame_iterations=10)
    t0 = time.perf_counter()
    track_sequences([seq], out / "track", TrackOptions(cfg, device=device, viz=True))
    seconds = (time.perf_counter() - t0) / len(theta)
    result = evaluate_sequence(out / "track" / "demo", SequenceLayout(seq).gt.root, with_penetration=False)
    (out / "eval.json").write_text(json.dumps(result, indent=2))
    return {"frames": len(theta), "seconds_per_frame": seconds, "mean_px": result["thesis_mean_px"],
            "mean_mm": result["mean_mm"], "auc_0_50mm": result["auc_0_50mm"]}
