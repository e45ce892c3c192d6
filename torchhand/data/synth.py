"""Synthetic RGB-D sequences: the thesis motions (or random poses) rendered with a
sensor noise model into the sequence layout of :mod:`torchhand.data.layout`.

Synthesis uses the same scene, skinning and renderer as tracking, so the ground
truth (theta, keypoints, per-pixel ids) is exact for the rendered images.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import List, NamedTuple, Optional, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchhand.geometry.camera import Camera, kinect_camera
from torchhand.io.assets import THESIS_MODEL_NAMES, load_demo_motion
from torchhand.io.thesis import FormatError, read_calibration, read_thesis_model, sequence_models
from torchhand.model.kinematics import so3_exp, so3_log
from torchhand.model.motion import motion_to_theta
from torchhand.geometry.render import Renderer, RenderResult
from torchhand.model.joints21 import scene_joint_names, scene_standard_joints
from torchhand.model.scene import Scene
from torchhand.io.output_dir import prepare_output_dir
from torchhand.data.layout import (Poses, SequenceInfo, SequenceLayout, write_depth, write_joints21, write_poses,
                                   write_rgb, write_sequence_info)
from torchhand.data.noise import apply_kinect_noise
from torchhand.data.noise_params import noise_model
from torchhand.data.appearance import background_texture, face_albedo, model_albedo, shade
from torchhand.data.ballan_protocol import protocol as noise_protocol, simulate_detections, structural_noise

__all__ = ["SyntheticFrames", "thesis_motion", "demo_motion", "random_poses", "write_synthetic_sequence", "shade_rgb",
           "quat_to_matrix", "with_camera_ring"]



@dataclass
class SyntheticFrames:
    """What to render: a scene, its poses (N, D), the cameras, provenance. ``hidden``:
    models that are rendered but left out of the sequence's declared scene and its
    ``gt/`` poses (an unknown object a scan must find; its ground truth is the caller's
    to write); their ids in ``gt/ids`` follow the declared models'."""

    scene: Scene
    theta: torch.Tensor
    cameras: List[Camera]
    name: str
    source: dict
    hidden: tuple = ()


def thesis_motion(hia_root, sequence: str, frames: Optional[slice] = None, dtype=torch.float64) -> SyntheticFrames:
    """Poses of a thesis sequence as theta of the shipped models.

    Video frame k uses MOTION row k + MotionnOffset (data README). Raises
    FormatError for a sequence without MOTION files.
    """
    hia_root = Path(hia_root)
    names, bounds = sequence_models(hia_root, sequence)
    rows = np.arange(bounds.total_aligned) + bounds.motion_offset
    rows = rows[frames] if frames is not None else rows
    if len(rows) == 0:
        raise ValueError(f"--frames selects no frame of sequence {sequence} ({bounds.total_aligned} frames)")
    models = [THESIS_MODEL_NAMES.get(n, n) for n in names]
    scene = Scene.from_names(models, dtype=dtype)
    thetas = []
    for thesis_name, model in zip(names, scene.models):
        files = read_thesis_model(hia_root / "Models" / sequence, thesis_name)
        if files.motion is None:
            raise FormatError(f"{hia_root / 'Models' / sequence / (thesis_name + '.MOTION')}: not found; sequence "
                              f"{sequence} has no MOTION files, so there is no motion to render")
        n_rows = len(next(iter(files.motion.values())))
        if rows.max() >= n_rows:
            raise FormatError(f"sequence {sequence}: frame rows up to {rows.max()} requested, MOTION has {n_rows}")
        # Row 0 is the rest pose the MOTION is expressed against (data README).
        thetas.append(motion_to_theta(model, {b: m[rows] for b, m in files.motion.items()},
                                      motion_rest={b: m[0] for b, m in files.motion.items()}))
    calib = read_calibration(hia_root / "Calibration" / "Cameras.txt")[0]
    T = np.eye(4)
    T[:3] = calib.Rt
    K = calib.K
    cam = Camera.from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480, T_cw=torch.as_tensor(T), name="kinect")
    source = {"format": "hands-in-action MOTION", "sequence": sequence,
              "video_frames": [int(rows[0] - bounds.motion_offset), int(rows[-1] - bounds.motion_offset)]}
    return SyntheticFrames(scene, torch.cat(thetas, 1), [cam], f"hia_{sequence}", source)


def demo_motion(frames: Optional[slice] = None, dtype=torch.float32) -> SyntheticFrames:
    """The shipped demo motion (two hands and the ball, a thesis excerpt) seen by the
    thesis' camera; needs no thesis data."""
    names, theta = load_demo_motion()
    theta = theta[frames] if frames is not None else theta
    if len(theta) == 0:
        raise ValueError("--frames selects no frame of the demo motion (60 frames)")
    return SyntheticFrames(Scene.from_names(names, dtype=dtype), theta.to(dtype), [kinect_camera(dtype=dtype)],
                           "demo", {"format": "shipped demo motion"})


def random_poses(models: Sequence[str], frames: int, seed: int = 0, distance=(400.0, 800.0),
                 dtype=torch.float64) -> SyntheticFrames:
    """Independent random poses within the joint limits, seen from random viewpoints.

    Joint angles are uniform within their limits; each model gets a uniformly random
    orientation and a position in the camera's view cone at ``distance`` mm (models
    of one frame are placed side by side around a common centre). For detector
    training; the frames are not a motion.
    """
    g = torch.Generator().manual_seed(seed)
    scene = Scene.from_names(models, dtype=dtype)
    cam = kinect_camera(dtype=dtype)
    lo, hi = scene.lower, scene.upper
    finite = torch.isfinite(lo) & torch.isfinite(hi)
    u = torch.rand(frames, scene.num_dofs, generator=g, dtype=dtype)
    theta = torch.where(finite, lo.nan_to_num(0) + u * (hi - lo).nan_to_num(0), torch.zeros_like(u))
    z = distance[0] + torch.rand(frames, generator=g, dtype=dtype) * (distance[1] - distance[0])
    centre = torch.stack([(torch.rand(frames, generator=g, dtype=dtype) - 0.5) * 0.4 * z,
                          (torch.rand(frames, generator=g, dtype=dtype) - 0.5) * 0.3 * z, z], 1)
    for k, (name, model) in enumerate(zip(scene.names, scene.models)):
        s = scene.slices[name]
        q = torch.randn(frames, 4, generator=g, dtype=dtype)
        q = q / q.norm(dim=1, keepdim=True)
        rotvec = so3_log(quat_to_matrix(q))
        # Place the model's vertex centroid (not its root joint) at its target position.
        offset = torch.tensor([(k - (len(models) - 1) / 2) * 120.0, 0.0, 0.0], dtype=dtype)
        c_rest = model.vertices_rest.mean(0)
        root = model.rest_transforms[0, :3, 3]
        R = so3_exp(rotvec)
        # position of the centroid after rotating about the root joint: R (c - root) + root + t
        t = centre + offset - ((R @ (c_rest - root)[:, None])[..., 0] + root)
        theta[:, s.start:s.start + 3] = t
        theta[:, s.start + 3:s.start + 6] = rotvec
    source = {"format": "random poses", "seed": seed, "models": list(models)}
    return SyntheticFrames(scene, theta, [cam], f"random_{seed}", source)


def with_camera_ring(frames: SyntheticFrames, views: int, scale: float = 1.0) -> SyntheticFrames:
    """``frames`` seen by :func:`~torchhand.geometry.camera_rig.camera_ring` of ``views``
    cameras, centred at the depth of the scene's first frame on camera 0's axis (camera
    0 keeps its place, so world coordinates are unchanged). ``scale`` enlarges every
    camera's image (:meth:`~torchhand.geometry.camera.Camera.scaled`: the same field of
    view, ``scale`` times the pixels in each direction)."""
    from torchhand.geometry.camera_rig import camera_ring

    if isinstance(views, bool) or not isinstance(views, int) or views < 1:
        raise ValueError(f"--views must be a positive number of cameras, got {views!r}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
        raise ValueError(f"--image-scale must be a number > 0, got {scale!r}")
    with torch.no_grad():
        v = frames.scene(frames.theta[:1].to(frames.scene.lower.dtype)).vertices[0]
    cam0 = frames.cameras[0]
    distance = float(cam0.to(dtype=v.dtype).to_camera(v[None])[0, :, 2].median())
    cams = camera_ring(views, distance, like=cam0 if scale == 1 else cam0.scaled(scale))
    source = {**frames.source, "views": views, "ring_distance_mm": round(distance, 1)}
    if scale != 1:
        source["image_scale"] = scale
    return dataclasses.replace(frames, cameras=[c.to(dtype=cam0.dtype) for c in cams], source=source)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(q.shape[:-1] + (3, 3))


def shade_rgb(result: RenderResult, albedo: torch.Tensor, light=(0.3, -0.4, -1.0), ambient: float = 0.35) -> torch.Tensor:
    """Plain Lambertian shading of a render. albedo: (M, 3) per model id.

    Returns (B, H, W, 3) uint8 RGB, a grey background where nothing is hit.
    """
    l = torch.as_tensor(light, dtype=result.normals.dtype, device=result.normals.device)
    l = l / l.norm()
    lambert = (result.normals @ l).clamp_min(0)  # light direction points to the camera side (-z)
    hit = result.model_id >= 0
    col = albedo.to(result.normals)[result.model_id.clamp_min(0)]
    rgb = col * (ambient + (1 - ambient) * lambert)[..., None]
    rgb = torch.where(hit[..., None], rgb, torch.full_like(rgb, 0.25))
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8)


def _salient_in_view(points: torch.Tensor, camera: Camera, depth: torch.Tensor, tolerance_mm: float = 4.0) -> tuple:
    """((B, P, 2) pixels, (B, P) seen) of (B, P, 3) world points in one camera's render:
    seen where the point is in the image and the rendered surface there is not nearer
    than ``tolerance_mm`` (the point is on the visible surface)."""
    uv = camera.project(points)
    z = camera.to_camera(points)[..., 2]
    H, W = depth.shape[-2:]
    u, v = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H) & (z > 0)
    b = torch.arange(points.shape[0], device=points.device)[:, None].expand_as(u)
    d = depth[b, v.clamp(0, H - 1), u.clamp(0, W - 1)]
    seen = inside & (d > 0) & (d >= z - tolerance_mm)
    return uv.cpu().numpy(), seen.cpu().numpy()


def write_synthetic_sequence(
    frames: SyntheticFrames,
    out,
    noise: str = "kinect",
    seed: int = 0,
    force: bool = False,
    rgb: bool = True,
    batch_size: int = 8,
    progress: bool = True,
    backend: Optional[str] = None,
    colour: str = "flat",
    depth: bool = True,
    protocol: Optional[str] = None,
) -> Path:
    """Render ``frames`` into a new sequence folder (see datasets/README.md).

    Depth (with the named noise model; none with ``depth=False``), optional RGB, and
    ground truth under ``gt/``. An existing non-empty ``out`` is refused unless
    ``force``. ``backend``: of the renders (:mod:`torchhand.geometry.raycast`; None:
    Warp when installed). ``colour``: ``"flat"`` (one colour per model, face normals,
    grey background) or ``"shaded"`` (:mod:`torchhand.data.appearance`: smooth shading,
    nails, a textured background per camera; also writes the nail centres to
    ``gt/salient_2d.npy`` and ``gt/salient_visible.npy``). ``protocol``: ``"ballan"``
    adds :mod:`torchhand.data.ballan_protocol`'s noise to the colour images (their
    circles in ``occluders/``) and writes simulated salient detections per camera
    (``salient.json``).
    """
    params, proto = _checked_settings(noise, protocol, colour, depth, rgb)
    out = prepare_output_dir(out, force)
    scene, theta, cams = frames.scene, frames.theta, frames.cameras
    shaded = rgb and colour == "shaded"
    acc = _Accumulated.empty(len(theta), len(cams), scene, shaded)
    seq = SequenceLayout(out)
    for c in range(len(cams)):
        for folder, wanted in ((seq.depth_dir(c), depth), (seq.rgb_dir(c), rgb), (seq.occluders_dir(c), proto)):
            if wanted:
                folder.mkdir(parents=True, exist_ok=True)
    seq.gt.ids_dir.mkdir(parents=True)
    looks = _Looks(face_albedo(scene) if shaded else model_albedo(scene),
                   [torch.as_tensor(background_texture(c.height, c.width, seed=1000 * seed + k))
                    for k, c in enumerate(cams)] if shaded else None, shaded, rgb, depth, params, proto)
    g, rng = torch.Generator().manual_seed(seed), np.random.default_rng(seed)
    bar = tqdm(total=len(theta), desc=f"synth {frames.name}", unit="frame", disable=not progress)
    renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id, backend=backend)
    for s in range(0, len(theta), batch_size):
        th = theta[s : s + batch_size].to(scene.lower.dtype)
        with torch.no_grad():
            posed = scene(th)
            joints21 = scene_standard_joints(scene, posed)
        for c, cam in enumerate(cams):
            _write_view(seq, renderer, (posed, joints21), cam, c, s, looks, acc, g, rng)
        bar.update(len(th))
    bar.close()
    source = {**frames.source, "noise": noise if depth else None, "seed": seed}
    if rgb:
        source["colour"] = colour
    _write_ground_truth(out, seq, frames, acc, source, rgb, depth, protocol, proto)
    return out


class _Looks(NamedTuple):
    """How :func:`write_synthetic_sequence` renders: albedo, backgrounds (per camera, or
    None), shaded, rgb, depth, the noise parameters and the protocol."""

    albedo: torch.Tensor
    backgrounds: Optional[list]
    shaded: bool
    rgb: bool
    depth: bool
    params: object
    proto: object


class _Accumulated(NamedTuple):
    """What the frames give the ground truth: keypoints (N, C, P, 3) mm and (N, C, P, 2)
    px; with shading the nail vertices, their centres (N, C, T, 2) and visibility, and
    each camera's simulated detections; the standard 21 joints of every hand (N, C, 21 x
    hands, 3) mm and (N, C, 21 x hands, 2) px."""

    kp3d: np.ndarray
    kp2d: np.ndarray
    nails: Optional[torch.Tensor]
    sal2d: Optional[np.ndarray]
    sal_vis: Optional[np.ndarray]
    detections: list
    joints21_3d: np.ndarray
    joints21_2d: np.ndarray

    @classmethod
    def empty(cls, N: int, C: int, scene, shaded: bool) -> "_Accumulated":
        P = len(scene.keypoint_names)
        nails = sal2d = sal_vis = None
        if shaded:
            from torchhand.model.fingertips import nail_vertices

            nails = nail_vertices(scene)  # empty without hands
            sal2d, sal_vis = np.zeros((N, C, len(nails), 2)), np.zeros((N, C, len(nails)), bool)
        H = len(scene_joint_names(scene))
        return cls(np.zeros((N, C, P, 3)), np.zeros((N, C, P, 2)), nails, sal2d, sal_vis, [[] for _ in range(C)],
                   np.zeros((N, C, H, 3)), np.zeros((N, C, H, 2)))


def _checked_settings(noise: str, protocol: Optional[str], colour: str, depth: bool, rgb: bool) -> tuple:
    """(noise parameters, protocol) of :func:`write_synthetic_sequence`'s settings, or a
    clear error before anything is written."""
    params = noise_model(noise)
    proto = noise_protocol(protocol)
    if colour not in ("flat", "shaded"):
        raise ValueError(f"colour must be 'flat' or 'shaded', got {colour!r}")
    if not (depth or rgb):
        raise ValueError("nothing to write: depth and rgb are both off")
    if proto is not None and not (rgb and colour == "shaded"):
        raise ValueError(f"protocol {protocol!r} perturbs colour images and nail detections: it needs rgb and "
                         "colour='shaded'")
    return params, proto


def _write_view(seq: SequenceLayout, renderer: Renderer, posed_joints, cam, c: int, s: int, looks: _Looks,
                acc: _Accumulated, g: torch.Generator, rng: np.random.Generator) -> None:
    """Camera ``c``'s frames s, s + 1, ... of the posed batch (the scene's output and its
    hands' 21 joints): depth, colour, occluders and ids written, keypoints, joints and
    nails into ``acc``."""
    posed, joints21 = posed_joints
    n = posed.vertices.shape[0]
    camd = cam.to(dtype=posed.vertices.dtype)
    res = renderer(posed.vertices, camd)
    dmap = res.depth
    if looks.params is not None and looks.depth:
        dmap = apply_kinect_noise(dmap, res.normals, camd.K.float(), looks.params, generator=g)
    acc.kp3d[s : s + n, c] = camd.to_camera(posed.keypoints).cpu().numpy()
    acc.kp2d[s : s + n, c] = camd.project(posed.keypoints).cpu().numpy()
    acc.joints21_3d[s : s + n, c] = camd.to_camera(joints21).cpu().numpy()
    acc.joints21_2d[s : s + n, c] = camd.project(joints21).cpu().numpy()
    if looks.shaded:
        image = shade(res, posed.vertices, renderer.faces, looks.albedo, camd, looks.backgrounds[c])
        acc.sal2d[s : s + n, c], acc.sal_vis[s : s + n, c] = _salient_in_view(posed.vertices[:, acc.nails], camd,
                                                                              res.depth)
    else:
        image = shade_rgb(res, looks.albedo) if looks.rgb else None
    for b in range(n):
        k = s + b
        if looks.depth:
            write_depth(seq.depth(k, c), dmap[b].cpu().numpy())
        if looks.rgb:
            img = image[b].cpu().numpy()
            if looks.proto is not None:
                img, circles = structural_noise(img, rng, looks.proto)
                cv2.imwrite(str(seq.occluders(k, c)), circles.astype(np.uint8) * 255)
                seen = acc.sal2d[k, c][acc.sal_vis[k, c]]
                acc.detections[c].append(simulate_detections(seen, rng, looks.proto, (cam.width, cam.height))
                                         .round(2).tolist())
            write_rgb(seq.rgb(k, c), img)
        if c == 0:
            ids = (res.model_id[b] + 1).clamp(0, 255).to(torch.uint8).cpu().numpy()
            cv2.imwrite(str(seq.gt.ids(k)), ids)


def _write_ground_truth(out, seq: SequenceLayout, frames: SyntheticFrames, acc: _Accumulated, source: dict, rgb: bool,
                        depth: bool, protocol: Optional[str], proto) -> None:
    """``sequence.json`` (with ``source``), the first frame's pose, ``gt/`` and the
    protocol's detections."""
    scene, theta, cams = frames.scene, frames.theta, frames.cameras
    listed = [n for n in scene.names if n not in frames.hidden]
    dofs = np.concatenate([np.arange(scene.slices[n].start, scene.slices[n].stop) for n in listed])
    kps = np.concatenate([np.arange(scene.keypoint_slices[n].start, scene.keypoint_slices[n].stop, dtype=np.int64)
                          for n in listed])
    if proto is not None:
        source["protocol"] = {"name": protocol, **dataclasses.asdict(proto)}
        for c in range(len(cams)):
            seq.salient(c).write_text(json.dumps(
                {"format": "torchhand-salient/1", "source": f"simulated detections of the nail centres, protocol "
                 f"{protocol} (torchhand.data.ballan_protocol)", "frames": acc.detections[c]}))
    if acc.sal2d is not None:
        np.save(seq.gt.salient_2d, acc.sal2d)
        np.save(seq.gt.salient_visible, acc.sal_vis)
    info = SequenceInfo(frames.name, cams, listed, len(theta), has_rgb=rgb, source=source, has_depth=depth)
    th = theta.cpu().numpy()[:, dofs]
    write_sequence_info(out, info, init_theta=th[0])
    write_poses(seq.gt, Poses(th, acc.kp3d[:, :, kps], acc.kp2d[:, :, kps], listed,
                              [scene.dof_names[d] for d in dofs], [scene.keypoint_names[k] for k in kps]))
    joints = [k for k, n in enumerate(scene_joint_names(scene)) if n.rsplit("/", 1)[0] in listed]
    if joints:
        write_joints21(seq.gt, acc.joints21_3d[:, :, joints], acc.joints21_2d[:, :, joints])
