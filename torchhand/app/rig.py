"""``torchhand rig``: a rigged model of an articulated object from a depth sequence of
it being bent (thesis Ch. 6, Algorithm 2).

1. With ``hands``, the hands are tracked first (:func:`~torchhand.app.runner.
   track_sequences`, their first pose from ``init_pose.json``, else the automatic
   initialisation) and their rendered
   silhouettes (dilated) are removed from the depth.
2. The template is placed on frame 0 (``template_pose``, else the rigid fit of the
   template onto the frame-0 pose of a model of the sequence with the same mesh) and
   tracked deformably (:mod:`~torchhand.reconstruction.deformable`, Eq. 6.1-6.5).
3. Its vertex trajectories are segmented by their motion (:mod:`~torchhand.
   reconstruction.motion_segments`, Eq. 6.6-6.12) and the model is rigged
   (:mod:`~torchhand.reconstruction.rigging`).
4. The sequence is tracked again with the rigged model (and the hands), articulated,
   with the tracker's energy (point-to-plane model-to-data, as for Table 6.2), from the
   rig's fit to the deformable frame 0.

Outputs, in a hidden partial folder renamed when complete:

- ``model.npz``: the rigged model (the template's vertices and faces, in their order),
  for ``torchhand track --models``;
- ``segments.ply``: the template coloured by part; ``skeleton.png``: the parts, the curve
  skeleton, the joints; ``skeleton.json``: the joints, the auxiliary joints, the curve
  skeleton and the construction's notes;
- ``deformable/vertices.npy``: (N, V, 3) float32 world mm, the deformable tracking;
- ``hands/``: the hands' first tracking (with ``hands``);
- ``track/``: the runner's outputs for the sequence tracked with the rigged model,
  with ``track/vertices/<model>.npy`` (camera 0's coordinates);
- ``rig_log.json``: the settings, the parts, the eigenvalues, per-frame pairs, timings.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from torchhand.app.drawing import draw_rig, part_colors
from torchhand.app.options import TrackOptions
from torchhand.app.runner import track_sequences
from torchhand.data.layout import SequenceLayout, read_depth, read_init_pose, read_poses, read_sequence_info
from torchhand.geometry.render import Renderer, model_masks
from torchhand.io.assets import find_model, load_assets, save_assets
from torchhand.io.mesh_files import check_mesh, read_object_mesh, write_mesh
from torchhand.io.output_dir import commit_dir, partial_dir, prepare_output_dir
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.scene import Scene
from torchhand.reconstruction.deformable import DeformConfig, track_deformable
from torchhand.reconstruction.motion_segments import segment_motion
from torchhand.reconstruction.rigging import RigConfig, build_rig, fit_rig
from torchhand.reconstruction.registration import kabsch
from torchhand.tracking.preprocess import PreprocessConfig, preprocess_depth

__all__ = ["rig_folder", "read_template", "RigError", "MIN_FRAMES", "ARTICULATED_MM"]

#: the fewest frames a rig is built from (the motion segmentation compares frames dt apart)
MIN_FRAMES = 10
#: the largest extent of a template: articulated objects reach beyond a hand-held size
ARTICULATED_MM = (10.0, 1500.0)


class RigError(ValueError):
    """The sequence or the template cannot be rigged (the message says why)."""


def read_template(template) -> tuple:
    """(vertices (V, 3) mm, faces (F, 3), what it is) of a template given as a mesh file
    (PLY, OFF, OBJ, STL: closed, in mm) or as a torchhand model (a name or ``.npz``: its
    rigging-pose mesh, e.g. the ``model.npz`` of ``torchhand scan``)."""
    p = Path(str(template))
    if p.suffix.lower() == ".npz" or (not p.suffix and not p.exists()):
        assets = load_assets(find_model(str(template)))
        v, f = assets.vertices, assets.faces
        import trimesh

        check_mesh(trimesh.Trimesh(v, f, process=False), f"template {template}", closed=True, size_mm=ARTICULATED_MM)
        return v, f, f"model {assets.name}"
    mesh = read_object_mesh(p, closed=True, size_mm=ARTICULATED_MM)
    return mesh.vertices, mesh.faces, str(p)


def _template_placement(root: Path, info, template: np.ndarray, template_pose) -> np.ndarray:
    """(4, 4) template -> world on frame 0."""
    if template_pose is not None:
        T = np.asarray(template_pose, np.float64)
        if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4) \
                or not np.allclose(T[3], [0, 0, 0, 1]):
            raise RigError(f"template_pose must be a rigid (4, 4) transform, got {T.tolist()}")
        return T
    theta = read_init_pose(root) if SequenceLayout(root).init_pose.is_file() else None
    if theta is not None:
        scene = Scene.from_names(info.models, dtype=torch.float64)
        if theta.shape == (scene.num_dofs,):
            with torch.no_grad():
                posed = scene(torch.as_tensor(theta)[None])
            for name, model in zip(scene.names, scene.models):
                if model.num_vertices == len(template):
                    rest = model.vertices_rest.numpy()
                    if np.abs(rest - template).max() < 1e-3 * np.ptp(template, 0).max():
                        v = posed.vertices[0, scene.vertex_slices[name]]
                        return kabsch(torch.as_tensor(template), v).numpy()
    raise RigError(f"{root}: where is the template on frame 0? None of the sequence's models {info.models} has the "
                   "template's mesh (its init_pose.json would place it); pass --template-pose with a 4x4 "
                   "template-to-world transform")


def rig_folder(root, template, out, hands: Sequence[str] = (), name: Optional[str] = None,
               template_pose=None, deform: DeformConfig = DeformConfig(), lambda_thr: float = 0.7,
               use_normals: bool = True, samples: int = 1000, config: RigConfig = RigConfig(),
               merge_ratio: float = 1.5, interval: str = "sequence", refine: bool = True,
               near: float = 200.0, far: float = 1500.0, dilation: int = 5, frames: Optional[int] = None,
               force: bool = False, progress: bool = True, track: bool = True) -> dict:
    """Rig the object of the sequence folder ``root`` (module docstring) into the new
    folder ``out``; returns the log (also ``rig_log.json``)."""
    if interval not in ("sequence", "thesis"):  # checked before minutes of tracking
        raise ValueError(f"interval must be 'sequence' or 'thesis', got {interval!r}")
    root = Path(root)
    info = read_sequence_info(root)
    n = info.frames if frames is None else min(int(frames), info.frames)
    if n < MIN_FRAMES:
        raise RigError(f"{root}: rigging needs at least {MIN_FRAMES} frames of the object being bent (the motion "
                       f"segmentation compares frames some time apart), the sequence has {n}")
    hands = list(hands)
    unknown = [h for h in hands if h not in info.models]
    if unknown:
        raise RigError(f"{root}: hands {unknown} are not in the sequence's models {info.models}")
    tv, tf, what = read_template(template)
    T0 = _template_placement(root, info, tv, template_pose)
    final = prepare_output_dir(out, force)
    work = partial_dir(final)
    try:
        log = _rig_into(work, root, info, n, tv, tf, what, T0, hands, name or f"rig_{info.name}", deform, lambda_thr,
                        use_normals, samples, config, near, far, dilation, progress, track, merge_ratio, interval, refine)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)  # nothing half-written stays behind
        raise
    commit_dir(work, final, force=True)
    return log


def _hand_masks(root: Path, work: Path, info, hands: list, n: int, dilation: int, progress: bool) -> tuple:
    """Track the hands (in camera 0, as the runner does), then (theta (n, D_hands), their
    masks in every camera (n, H, W))."""
    starts = None  # without init_pose.json: the runner's automatic initialisation of the hands
    init_pose = SequenceLayout(root).init_pose
    if init_pose.is_file():
        full = Scene.from_names(info.models, dtype=torch.float64)
        th0 = read_init_pose(root)
        if th0.shape != (full.num_dofs,):
            raise RigError(f"{init_pose}: {th0.size} values, the sequence's models {info.models} have "
                           f"{full.num_dofs} DoF")
        starts = [np.concatenate([th0[full.slices[h]] for h in hands])]
    summary = track_sequences([root], work, TrackOptions(models=tuple(hands), reinit_iou=0.0), names=["hands"],
                              init_poses=starts, progress=progress)[0]
    if summary["status"] != "ok":
        raise RigError(f"{root}: the hands could not be tracked: {summary.get('error')}")
    scene = Scene.from_names(hands, dtype=torch.float64)
    theta = torch.as_tensor(read_poses(work / "hands").theta[:n])
    with torch.no_grad():
        verts = scene(theta).vertices
    renderer = Renderer(scene.faces)
    masks = [model_masks(renderer, verts, cam.to(dtype=torch.float64), dilation) for cam in info.cameras]
    return theta.numpy(), masks


def _rig_into(work: Path, root: Path, info, n: int, tv, tf, what: str, T0: np.ndarray, hands: list, name: str,
              deform: DeformConfig, lambda_thr: float, use_normals: bool, samples: int, config: RigConfig,
              near: float, far: float, dilation: int, progress: bool, track: bool, merge_ratio: float,
              interval: str, refine: bool) -> dict:
    t0 = time.perf_counter()
    seconds = {}
    hand_theta, masks = None, None
    if hands:
        hand_theta, masks = _hand_masks(root, work, info, hands, n, dilation, progress)
        seconds["hand_tracking"] = time.perf_counter() - t0
    pre = PreprocessConfig(near=near, far=far)

    def object_frames():
        for f in range(n):
            views = []
            for c, cam in enumerate(info.cameras):
                d = read_depth(SequenceLayout(root).depth(f, c), info.depth_unit_mm)
                d = np.where((d >= near) & (d <= far), d, 0).astype(np.float32)
                if masks is not None:
                    d[masks[c][f]] = 0
                if not (d > 0).any():
                    after = " once the hands are removed" if hands else ""
                    raise RigError(f"{SequenceLayout(root).depth(f, c)}: no depth of the object is left "
                                   f"between {near:g} and {far:g} mm{after}")
                views.append(preprocess_depth(d, cam, pre))
            yield views

    placed = tv @ T0[:3, :3].T + T0[:3, 3]
    t1 = time.perf_counter()
    res = track_deformable(placed, tf, object_frames(), info.cameras, deform, num_frames=n, progress=progress,
                           desc=f"deformable {info.name}")
    seconds["deformable"] = time.perf_counter() - t1
    (work / "deformable").mkdir()
    np.save(work / "deformable" / "vertices.npy", res.vertices)
    # the trajectories in the template's frame: the rig keeps the template's coordinates
    inv = np.linalg.inv(T0)
    traj = res.vertices.astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]
    t2 = time.perf_counter()
    seg = segment_motion(traj, tv, tf, lambda_thr=lambda_thr, samples=samples, use_normals=use_normals,
                         merge_ratio=merge_ratio, interval=interval, refine=refine)
    rig = build_rig(tv, tf, traj, seg.labels, name, config, source=f"torchhand rig of {root} ({what})")
    seconds["rigging"] = time.perf_counter() - t2
    save_assets(rig.assets, work / "model.npz")
    write_mesh(work / "segments.ply", tv, tf, colors=part_colors(seg.parts)[seg.labels])
    import cv2

    cv2.imwrite(str(work / "skeleton.png"), draw_rig(tv, seg.labels, rig.skeleton.nodes, rig.skeleton.edges,
                                                     rig.joints, rig.ends, rig.branches))
    (work / "skeleton.json").write_text(json.dumps(rig.to_json()))
    log = {"sequence": str(root), "template": what, "frames": n, "name": name, "parts": seg.parts,
           "clusters": seg.clusters, "eigenvalues": seg.eigenvalues.round(5).tolist(), "dt": seg.dt,
           "joints_mm": rig.joints.round(3).tolist(), "joint_dofs": rig.joint_dofs.tolist(), "notes": list(seg.refined) + list(seg.merged) + rig.notes,
           "deformable": {"model_to_data": res.model_to_data.tolist(), "data_to_model": res.data_to_model.tolist(),
                          "seconds": res.seconds.round(4).tolist()},
           "template_pose": T0.tolist(), "hands": hands,
           "settings": {"deform": dataclasses.asdict(deform), "lambda_thr": lambda_thr, "use_normals": use_normals,
                        "merge_ratio": merge_ratio, "interval": interval, "refine": refine,
                        "samples": samples, "rig": dataclasses.asdict(config), "near": near, "far": far,
                        "dilation": dilation}}
    if seg.parts == 1:
        print(f"{info.name}: {rig.notes[0]}")
    if track:
        model = ArticulatedModel(rig.assets, dtype=torch.float64)
        th_obj = fit_rig(model, res.vertices[0]).numpy()  # the rig's pose on the deformable frame 0 (world)
        start = np.concatenate([hand_theta[0], th_obj]) if hands else th_obj
        t3 = time.perf_counter()
        options = TrackOptions(models=(*hands, str(work / "model.npz")), reinit_iou=0.0, write_vertices=True)
        summary = track_sequences([root], work, options, names=["track"], init_poses=[start], progress=progress)[0]
        seconds["tracking"] = time.perf_counter() - t3
        if summary["status"] != "ok":
            raise RigError(f"{root}: tracking with the rigged model failed: {summary.get('error')}")
        log["track"] = {k: summary[k] for k in ("frames", "seconds_per_frame", "mean_iou", "median_depth_residual_mm")}
    seconds["total"] = time.perf_counter() - t0
    log["seconds"] = seconds
    (work / "rig_log.json").write_text(json.dumps(log, indent=1))
    return log
