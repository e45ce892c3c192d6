"""``torchhand scan``: in-hand scanning of a sequence folder (thesis Ch. 5).

The hand is tracked first (:func:`~torchhand.app.runner.track_sequences` with the
skin-colour segmentation, so the held object is unknown data to the hand tracker, not
free space), its rendered silhouette (dilated) and the skin-coloured pixels are removed
from the depth, and :func:`~torchhand.reconstruction.in_hand.scan` reconstructs the
object from what is left. The outputs go to a hidden partial folder renamed when
complete:

- ``model.npz``: a rigid torchhand model of the closed surface (its origin at the
  surface's centroid), for ``torchhand track --models hand_right,OUT/model.npz``;
- ``mesh.ply``: the same surface; ``object_pose.npy``: (N, 4, 4) model -> camera per
  frame (camera 0's coordinates); ``object_theta.npy`` (N, 6), the model's theta as
  ``init_pose.json`` and the tracker take it (world frame; NaN where not registered);
- ``hand/``: the hand's tracking (the runner's outputs);
- ``overlays/NNNNNN.png``: every ``overlay_every``-th frame: the depth, the removed hand
  pixels, and the outline of the reconstruction at the frame's estimated pose;
- ``scan_log.json``: per frame the contact vertices, ICP pairs and seconds; the mesh's
  size and whether it is watertight; the settings.

``baseline=True`` runs the KinectFusion-style baseline instead: the raw depth in range,
hand and all, aligned frame to model by ICP alone, no hand tracking.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchhand.app.drawing import depth_to_color, depth_range, draw_mask_outline
from torchhand.app.options import TrackOptions
from torchhand.app.runner import track_sequences
from torchhand.data.layout import OutputLayout, SequenceLayout, read_depth, read_poses, read_rgb, read_sequence_info
from torchhand.geometry.render import Renderer, model_masks
from torchhand.io.assets import rigid_assets, save_assets
from torchhand.io.mesh_files import write_mesh
from torchhand.io.output_dir import commit_dir, partial_dir, prepare_output_dir
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.kinematics import so3_log
from torchhand.model.scene import Scene
from torchhand.model.shape import finger_bones
from torchhand.reconstruction.in_hand import ScanConfig, ScanError, ScanResult, scan
from torchhand.tracking.segmentation import SegmentConfig, skin_mask

__all__ = ["scan_folder", "ScanError"]


def _effectors(hand: ArticulatedModel) -> list:
    """Vertex ids of the distal bone of each finger (the thesis' end-effectors)."""
    return [torch.nonzero(hand.vertex_bone == int(bones[-1]))[:, 0] for bones in finger_bones(hand).values()]


def scan_folder(root, out, hand: str = "hand_right", force: bool = False, config: ScanConfig = ScanConfig(),
                baseline: bool = False, near: float = 200.0, far: float = 1500.0, dilation: int = 5, erode: int = 0, reinit_iou: float = 0.0,
                overlay_every: int = 10, progress: bool = True) -> dict:
    """Scan the object of the sequence folder ``root`` into the new folder ``out``
    (module docstring). Returns the scan log (also written as ``scan_log.json``)."""
    root = Path(root)
    info = read_sequence_info(root)
    if info.frames < 2:
        raise ScanError(f"{root}: a scan needs at least 2 frames, the sequence has {info.frames}")
    final = prepare_output_dir(out, force)
    work = partial_dir(final)
    try:
        return _scan_into(work, final, root, info, hand, config, baseline, near, far, dilation, erode, reinit_iou,
                          overlay_every, progress)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)  # nothing half-written stays behind
        raise


def _scan_into(work: Path, final: Path, root: Path, info, hand: str, config: ScanConfig, baseline: bool, near: float,
               far: float, dilation: int, erode: int, reinit_iou: float, overlay_every: int, progress: bool) -> dict:
    cam = info.cameras[0]
    t0 = time.perf_counter()
    hands = None
    effectors = None
    hand_masks = None
    track_seconds = 0.0
    if not baseline:
        if not info.has_rgb:
            raise ScanError(f"{root}: in-hand scanning segments the hand by skin colour and needs rgb/ frames")
        segment = SegmentConfig(mode="skin", near=near, far=far)
        options = TrackOptions(segment=segment, models=(hand,), reinit_iou=reinit_iou)
        summary = track_sequences([root], work, options, names=["hand"], progress=progress)[0]
        if summary["status"] != "ok":
            raise ScanError(f"{root}: the hand could not be tracked: {summary.get('error')}")
        track_seconds = time.perf_counter() - t0
        scene = Scene.from_names([hand], dtype=torch.float64)
        theta = torch.as_tensor(read_poses(work / "hand").theta)
        with torch.no_grad():
            verts = scene(theta).vertices
        camd = cam.to(dtype=torch.float64)
        hand_masks = model_masks(Renderer(scene.faces), verts, camd, dilation)
        hands = list(camd.to_camera(verts))  # the scan works in camera coordinates
        effectors = _effectors(scene.models[0])

    def object_depths():
        for f in range(info.frames):
            d = read_depth(SequenceLayout(root).depth(f), info.depth_unit_mm)
            d = np.where((d >= near) & (d <= far), d, 0).astype(np.float32)
            if not baseline:
                rgb = read_rgb(SequenceLayout(root).rgb(f))
                d[hand_masks[f] | skin_mask(rgb)] = 0
                if erode:  # the object's outline: mixed and noisy pixels of the sensor
                    d[cv2.erode((d > 0).astype(np.uint8), np.ones((2 * erode + 1,) * 2, np.uint8)) == 0] = 0
                _check_in_view(d, f, root)
            yield d

    t1 = time.perf_counter()
    result = scan(object_depths(), cam.K.double().numpy(), cam.width, cam.height, hands, effectors, config,
                  frames=info.frames, progress=progress, desc=f"{'baseline ' if baseline else ''}scan {info.name}")
    scan_seconds = time.perf_counter() - t1
    log = _write_outputs(work, root, info, result, baseline, hand_masks, overlay_every, config)
    log["seconds"] = {"total": time.perf_counter() - t0, "hand_tracking": track_seconds, "scan": scan_seconds,
                      "per_frame": (time.perf_counter() - t0) / info.frames}
    (work / "scan_log.json").write_text(json.dumps(log, indent=1))
    commit_dir(work, final, force=True)
    return log


def _check_in_view(d: np.ndarray, f: int, root: Path) -> None:
    seen = d > 0
    n = int(seen.sum())
    if n == 0:
        return
    border = int(seen[0].sum() + seen[-1].sum() + seen[:, 0].sum() + seen[:, -1].sum())
    if border > 0.01 * n and border > 20:
        raise ScanError(f"{root}: frame {f}: the object leaves the view ({border} of its {n} pixels on the image "
                        "border); a scan needs the whole object in the image")


def _write_outputs(work: Path, root: Path, info, result: ScanResult, baseline: bool, hand_masks, every: int,
                   config: ScanConfig) -> dict:
    mesh = result.mesh
    centre = mesh.vertices.mean(0) if len(mesh.vertices) else np.zeros(3)
    verts = mesh.vertices - centre
    to_model = np.eye(4)
    to_model[:3, 3] = centre  # model coords -> object frame
    poses = result.poses @ to_model  # model -> camera
    np.save(work / "object_pose.npy", poses)
    # theta as the tracker's scene takes it (world frame: camera 0's T_cw undone); NaN
    # rows where the object was not registered
    world = np.linalg.inv(info.cameras[0].T_cw.double().numpy()) @ np.nan_to_num(poses)
    th = np.concatenate([world[:, :3, 3], so3_log(torch.as_tensor(world[:, :3, :3])).numpy()], 1)
    th[~np.isfinite(poses).all((1, 2))] = np.nan
    np.save(work / "object_theta.npy", th)
    if len(mesh.faces):
        write_mesh(work / "mesh.ply", verts, mesh.faces)
        name = f"scan_{info.name}"
        save_assets(rigid_assets(name, verts, mesh.faces, source=f"torchhand scan of {root}"), work / "model.npz")
        _write_overlays(work, root, info, verts, mesh.faces, poses, result.fused, hand_masks, every)
    sec = result.seconds
    return {"sequence": str(root), "baseline": baseline, "frames": int(len(result.poses)),
            "fused_frames": int(result.fused.sum()), "watertight": bool(mesh.watertight),
            "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "marching_cubes_faces": int(mesh.raw_faces),
            "contacts": result.contacts.tolist(), "icp_pairs": result.icp_pairs.tolist(),
            "scan_seconds_per_frame": sec.tolist(),
            "settings": {"registration": dataclasses.asdict(config.registration),
                         "contacts": dataclasses.asdict(config.contacts),
                         "fusion": dataclasses.asdict(config.fusion), "points": config.points,
                         "model_voxel": config.model_voxel, "min_points": config.min_points,
                         "lost_frames": config.lost_frames, "refine_passes": config.refine_passes}}


def _write_overlays(work: Path, root: Path, info, verts, faces, poses, fused, hand_masks, every: int) -> None:
    out = OutputLayout(work)  # the overlays as a tracker's output folder has them
    out.overlays_dir.mkdir()
    cam = info.cameras[0].to(dtype=torch.float64)
    to_world = torch.linalg.inv(cam.T_cw)  # the poses are model -> camera; the renderer takes world points
    renderer = Renderer(torch.as_tensor(faces))
    V = torch.as_tensor(verts)
    for f in range(0, len(poses), max(1, every)):
        d = read_depth(SequenceLayout(root).depth(f), info.depth_unit_mm)
        img = depth_to_color(d, *depth_range([d]))  # BGR
        if hand_masks is not None:
            img[hand_masks[f]] = (0.5 * img[hand_masks[f]] + 0.5 * np.array([120, 160, 230])).astype(np.uint8)
        if fused[f] and np.isfinite(poses[f]).all():
            P = to_world @ torch.as_tensor(poses[f])
            res = renderer((V @ P[:3, :3].T + P[:3, 3])[None], cam, normals=False)
            draw_mask_outline(img, (res.model_id[0] >= 0).numpy(), (60, 220, 60))
        cv2.imwrite(str(out.overlay(f)), img)
