"""Training and evaluation frames for the fingertip detector.

Frames are rendered with the project's own scene, skinning, ray caster and Kinect
noise model (:mod:`torchhand.data.synth`, :mod:`torchhand.geometry.render`,
:mod:`torchhand.data.noise`), optionally in front of a random background.

Ground-truth fingertips (thesis Fig. 4.2 d-f): the centre of a fingertip is the mean of
the posed vertices of its ``<finger>_tip`` vertex group, projected into the image. Its
visibility is measured by the renderer: the area (mm^2, at the fingertip's depth) of
the pixels whose ray hits a triangle of the group and where the sensor measured a
depth, ``n_pixels * (z / f)^2``. A fingertip with at least ``visible_mm2`` is a
ground-truth point; one with less but at least one pixel is "barely visible" (ignored
by the evaluation and by the training loss). Pixels the sensor left invalid (nearer
than the Kinect's 400 mm, in a projector shadow, at grazing angles) do not count: a
fingertip that the depth frame does not show cannot be detected from it.

Colour frames (``modality="colour"``, Ballan et al. 2012 Sec. 4.1: the salient points
are the finger nails): the scene is shaded by :mod:`torchhand.data.appearance` (skin,
pale nails, smooth light, a textured background drawn anew for every frame) and seen by
a ring of eight cameras around it (:func:`torchhand.data.synth.with_camera_ring`; frame
``k`` by camera ``k mod 8``), so that backs, palms and sides of the hands all occur. The
ground-truth point of a finger is the projection of its nail vertex
(:func:`torchhand.model.fingertips.nail_vertices`, the point the tracker's ``S`` term
pulls on) and its visible area counts the rendered pixels of its nail faces only: a
finger seen from the palm side has no visible nail. Optionally, a share of the frames
gets the structural noise of Ballan's protocol (:func:`torchhand.data.ballan_protocol.
structural_noise`: 100 bright or dark circles).
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional

import numpy as np
import torch
from tqdm import tqdm

from torchhand.data.appearance import background_texture, face_albedo, shade
from torchhand.data.ballan_protocol import structural_noise
from torchhand.data.noise import apply_kinect_noise
from torchhand.data.noise_params import noise_model
from torchhand.data.synth import SyntheticFrames, with_camera_ring
from torchhand.geometry.camera import Camera
from torchhand.geometry.render import Renderer
from torchhand.model.fingertips import FingertipSets, fingertip_faces, nail_faces, nail_vertices

__all__ = ["FingertipTargets", "SalientFrames", "fingertip_targets",
           "random_background", "render_salient_frames", "concat_frames", "save_frames", "load_frames",
           "VISIBLE_MM2", "VISIBLE_NAIL_MM2", "visible_mm2", "nail_sets", "RING_VIEWS"]

#: Visible fingertip area (mm^2) from which a fingertip is a ground-truth point (depth).
VISIBLE_MM2 = 30.0
#: Visible nail area (mm^2) from which a nail is a ground-truth point (colour).
VISIBLE_NAIL_MM2 = 15.0
#: Cameras of the ring that sees the colour frames.
RING_VIEWS = 8


def visible_mm2(frames: "SalientFrames") -> float:
    """The ground-truth area threshold of ``frames``' modality."""
    return VISIBLE_NAIL_MM2 if frames.image.ndim == 4 else VISIBLE_MM2


class FingertipTargets(NamedTuple):
    """Fingertips of the P = 5 * (number of hands) fingertips of a scene, per frame.

    Attributes:
        uv: (B, P, 2) projected fingertip centres (px; u = column, v = row).
        depth: (B, P) camera-frame z (mm) of the centres.
        area_mm2: (B, P) visible area of the fingertip surface (mm^2), 0 if hidden or
            outside the image.
    """

    uv: torch.Tensor
    depth: torch.Tensor
    area_mm2: torch.Tensor


class SalientFrames(NamedTuple):
    """Rendered frames with salient point ground truth (numpy, CPU).

    Attributes:
        image: (N, H, W) uint16 noisy depth (mm), 0 = invalid; or (N, H, W, 3) uint8
            RGB for colour frames (the modality follows from the shape).
        uv: (N, P, 2) float32 fingertip centres (nail vertices for colour) (px), P
            padded to 10 with NaN.
        tip_depth: (N, P) float32 camera-frame z (mm) of the centres; NaN for padding.
        area_mm2: (N, P) float32 visible fingertip (nail) area; 0 for padding.
        source: (N,) str name of the sequence / random set of each frame.
    """

    image: np.ndarray
    uv: np.ndarray
    tip_depth: np.ndarray
    area_mm2: np.ndarray
    source: np.ndarray


def fingertip_targets(vertices: torch.Tensor, face_id: torch.Tensor, camera: Camera, tips: FingertipSets,
                      sensed: Optional[torch.Tensor] = None) -> FingertipTargets:
    """Projected fingertip centres and their visible area.

    Args:
        vertices: (B, V, 3) posed scene vertices (world frame, mm).
        face_id: (B, H, W) ``RenderResult.face_id`` of the same frames (-1 = empty).
        camera: the camera the frames were rendered with.
        tips: :func:`torchhand.model.fingertips.fingertip_faces` of the scene.
        sensed: (B, H, W) bool, the pixels with a valid depth measurement (e.g. the
            noisy depth > 0); only these count towards the visible area. None: all.
    """
    index, mask, face_tip, _ = tips
    B, P = vertices.shape[0], index.shape[0]
    dev = vertices.device
    index, mask, face_tip = index.to(dev), mask.to(dev), face_tip.to(dev)
    w = mask.to(vertices.dtype) / mask.sum(1, keepdim=True).clamp_min(1)
    centre = (vertices[:, index] * w[None, :, :, None]).sum(2)  # (B, P, 3)
    cam = camera.to(device=dev, dtype=vertices.dtype)
    uv = cam.project(centre)
    z = cam.to_camera(centre)[..., 2]
    fid = face_id.to(dev)
    tip_px = torch.where(fid >= 0, face_tip[fid.clamp_min(0)], torch.full_like(fid, -1))
    if sensed is not None:
        if sensed.shape != fid.shape:
            raise ValueError(f"sensed has shape {tuple(sensed.shape)}, the renders {tuple(fid.shape)}")
        tip_px = torch.where(sensed.to(dev), tip_px, torch.full_like(tip_px, -1))
    counts = vertices.new_zeros(B, P + 1)
    counts.scatter_add_(1, torch.where(tip_px >= 0, tip_px, P).flatten(1), torch.ones_like(tip_px, dtype=vertices.dtype).flatten(1))
    f = cam.K[0, 0]
    area = counts[:, :P] * (z.clamp_min(1.0) / f) ** 2
    return FingertipTargets(uv, z, area)


def random_background(far_mm: torch.Tensor, height: int, width: int, generator: torch.Generator,
                      p_plane: float = 0.7, max_boxes: int = 4, max_spheres: int = 0,
                      focal_px: float = 525.0) -> torch.Tensor:
    """Random background depth behind the foreground: a tilted plane, boxes and spheres.

    Everything lies at least 20 mm behind ``far_mm`` (the farthest foreground point
    of each frame), so it never occludes the rendered models.

    Args:
        far_mm: (B,) farthest foreground depth per frame.
        height, width: image size.
        generator: CPU generator (all draws are made on the CPU).
        max_spheres: up to this many spheres of radius 10-40 mm per frame (rounded
            blobs like fingertips: negatives for the detector); 0 draws nothing more,
            so the other draws stay as without them.
        focal_px: focal length of the camera, for the spheres' image size.

    Returns:
        (B, H, W) float32 depth (mm), 0 where there is no background.
    """
    B = far_mm.shape[0]
    far = far_mm.float().cpu()

    def U(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=generator)

    v = torch.arange(height, dtype=torch.float32)[:, None] - height / 2
    u = torch.arange(width, dtype=torch.float32)[None, :] - width / 2
    z0 = far + U(30.0, 600.0, B)
    plane = z0[:, None, None] + U(-1.0, 1.0, B)[:, None, None] * u + U(-1.0, 1.0, B)[:, None, None] * v
    plane = torch.maximum(plane, (far + 20.0)[:, None, None])
    use = (torch.rand(B, generator=generator) < p_plane)[:, None, None]
    bg = torch.where(use, plane, torch.full_like(plane, float("inf")))
    n_boxes = torch.randint(0, max_boxes + 1, (B,), generator=generator)
    rows = torch.arange(height)[None, :, None]
    cols = torch.arange(width)[None, None, :]
    for k in range(max_boxes):
        on = (n_boxes > k)[:, None, None]
        h = torch.randint(10, height // 2, (B,), generator=generator)
        w = torch.randint(10, width // 2, (B,), generator=generator)
        r0 = (torch.rand(B, generator=generator) * (height - h)).long()
        c0 = (torch.rand(B, generator=generator) * (width - w)).long()
        inside = ((rows >= r0[:, None, None]) & (rows < (r0 + h)[:, None, None])
                  & (cols >= c0[:, None, None]) & (cols < (c0 + w)[:, None, None]))
        zb = (far + U(20.0, 400.0, B))[:, None, None] + U(-0.3, 0.3, B)[:, None, None] * (cols - c0[:, None, None])
        bg = torch.where(on & inside, torch.minimum(bg, zb.expand_as(bg)), bg)
    if max_spheres > 0:
        n_spheres = torch.randint(0, max_spheres + 1, (B,), generator=generator)
        for k in range(max_spheres):
            radius = U(10.0, 40.0, B)
            zc = far + 20.0 + radius + U(0.0, 150.0, B)  # its front behind far + 20, mostly before the plane
            uc, vc = U(0.0, width, B), U(0.0, height, B)
            d2 = ((cols - uc[:, None, None]) ** 2 + (rows - vc[:, None, None]) ** 2) * (zc / focal_px)[:, None, None] ** 2
            inside = (d2 < radius[:, None, None] ** 2) & (n_spheres > k)[:, None, None]
            zs = zc[:, None, None] - (radius[:, None, None] ** 2 - d2).clamp_min(0).sqrt()
            bg = torch.where(inside, torch.minimum(bg, zs), bg)
    return torch.where(torch.isfinite(bg), bg, torch.zeros_like(bg))


def nail_sets(scene) -> FingertipSets:
    """:class:`FingertipSets` of the scene's nails for :func:`fingertip_targets`: each
    finger's nail vertex as its only vertex (the projected point) and its nail faces as
    its faces (the visible area)."""
    tips = fingertip_faces(scene)
    index = nail_vertices(scene)[:, None]
    face_tip = torch.where(nail_faces(scene), tips.face_tip, torch.full_like(tips.face_tip, -1))
    return FingertipSets(index, torch.ones_like(index, dtype=torch.bool), face_tip, tips.names)


def render_salient_frames(
    frames: SyntheticFrames,
    seed: int = 0,
    background: bool = True,
    noise: Optional[str] = "kinect",
    batch_size: int = 8,
    progress: bool = True,
    max_tips: int = 10,
    spheres: int = 0,
    modality: str = "depth",
    circles: float = 0.0,
) -> SalientFrames:
    """Render frames with salient point ground truth (see the module docstring).

    Args:
        frames: poses and camera (e.g. :func:`torchhand.data.synth.thesis_motion` or
            :func:`~torchhand.data.synth.random_poses`); the first camera is used for
            depth, a ring of :data:`RING_VIEWS` around it for colour.
        seed: seeds backgrounds and sensor noise.
        background: composite a :func:`random_background` behind the models (depth),
            a :func:`~torchhand.data.appearance.background_texture` (colour; a grey
            background without).
        noise: sensor noise model name (:func:`torchhand.data.noise_params.noise_model`), or
            None (depth only).
        max_tips: P of the output arrays (10 = two hands).
        spheres: at most this many distractor spheres in each background
            (:func:`random_background`'s ``max_spheres``; depth only).
        modality: ``"depth"`` or ``"colour"``.
        circles: share of the colour frames that get Ballan's structural noise.
    """
    if modality == "colour":
        return _render_colour(frames, seed, background, batch_size, progress, max_tips, circles)
    if modality != "depth":
        raise ValueError(f"modality must be 'depth' or 'colour', got {modality!r}")
    params = noise_model(noise) if noise is not None else None
    g = torch.Generator().manual_seed(seed)
    scene, theta = frames.scene, frames.theta
    cam = frames.cameras[0]
    tips = fingertip_faces(scene)
    P = len(tips[3])
    if P > max_tips:
        raise ValueError(f"scene {scene.names} has {P} fingertips, more than max_tips={max_tips}")
    N, H, W = len(theta), cam.height, cam.width
    out_depth = np.zeros((N, H, W), np.uint16)
    out_uv = np.full((N, max_tips, 2), np.nan, np.float32)
    out_z = np.full((N, max_tips), np.nan, np.float32)
    out_area = np.zeros((N, max_tips), np.float32)
    bar = tqdm(total=N, desc=f"render {frames.name}", unit="frame", disable=not progress, leave=False)
    renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id)
    for s in range(0, N, batch_size):
        th = theta[s: s + batch_size].to(scene.lower.dtype)
        with torch.no_grad():
            verts = scene(th).vertices
        camd = cam.to(dtype=verts.dtype)
        res = renderer(verts, camd)
        depth = res.depth
        normals = res.normals
        if background:
            far = torch.where(depth > 0, depth, torch.zeros_like(depth)).flatten(1).amax(1)
            far = torch.where(far > 0, far, torch.full_like(far, 600.0))
            bg = random_background(far, H, W, g, max_spheres=spheres, focal_px=float(cam.K[0, 0])).to(depth.device)
            hit = depth > 0
            depth = torch.where(hit, depth, bg)
            normals = None  # estimated from the composite depth by the noise model
        if params is not None:
            depth = apply_kinect_noise(depth, normals, camd.K.float(), params, generator=g)
        t = fingertip_targets(verts, res.face_id, camd, tips, sensed=depth > 0)
        b = len(th)
        out_depth[s: s + b] = depth.round().clamp(0, 65535).cpu().numpy().astype(np.uint16)
        out_uv[s: s + b, :P] = t.uv.float().cpu().numpy()
        out_z[s: s + b, :P] = t.depth.float().cpu().numpy()
        out_area[s: s + b, :P] = t.area_mm2.float().cpu().numpy()
        bar.update(b)
    bar.close()
    return SalientFrames(out_depth, out_uv, out_z, out_area, np.array([frames.name] * N))


def _render_colour(frames: SyntheticFrames, seed: int, background: bool, batch_size: int, progress: bool,
                   max_tips: int, circles: float) -> SalientFrames:
    """The colour branch of :func:`render_salient_frames`."""
    if not 0.0 <= circles <= 1.0:
        raise ValueError(f"circles must be a share in [0, 1], got {circles}")
    rng = np.random.default_rng(seed)
    scene, theta = frames.scene, frames.theta
    cams = with_camera_ring(frames, RING_VIEWS).cameras
    tips = nail_sets(scene)
    P = len(tips.names)
    if P > max_tips:
        raise ValueError(f"scene {scene.names} has {P} nails, more than max_tips={max_tips}")
    albedo = face_albedo(scene)
    N, H, W = len(theta), cams[0].height, cams[0].width
    out_rgb = np.zeros((N, H, W, 3), np.uint8)
    out_uv = np.full((N, max_tips, 2), np.nan, np.float32)
    out_z = np.full((N, max_tips), np.nan, np.float32)
    out_area = np.zeros((N, max_tips), np.float32)
    bar = tqdm(total=N, desc=f"render {frames.name}", unit="frame", disable=not progress, leave=False)
    renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id)
    for c, cam in enumerate(cams):
        idx = np.arange(c, N, len(cams))
        for s in range(0, len(idx), batch_size):
            sel = idx[s: s + batch_size]
            th = theta[torch.as_tensor(sel)].to(scene.lower.dtype)
            with torch.no_grad():
                verts = scene(th).vertices
            camd = cam.to(dtype=verts.dtype)
            res = renderer(verts, camd)
            rgb = shade(res, verts, scene.faces, albedo, camd).cpu().numpy()
            empty = (res.face_id < 0).cpu().numpy()
            for b, k in enumerate(sel):
                img = rgb[b]
                if background:  # a new room for every frame
                    bg = background_texture(H, W, seed=int(rng.integers(2 ** 31)))
                    img[empty[b]] = (bg[empty[b]] * 255).round().astype(np.uint8)
                if rng.uniform() < circles:
                    img = structural_noise(img, rng)[0]
                out_rgb[k] = img
            t = fingertip_targets(verts, res.face_id, camd, tips)
            out_uv[sel, :P] = t.uv.float().cpu().numpy()
            out_z[sel, :P] = t.depth.float().cpu().numpy()
            out_area[sel, :P] = t.area_mm2.float().cpu().numpy()
            bar.update(len(sel))
    bar.close()
    return SalientFrames(out_rgb, out_uv, out_z, out_area, np.array([frames.name] * N))


def concat_frames(parts: List[SalientFrames]) -> SalientFrames:
    """Concatenate :class:`SalientFrames` along the frame axis."""
    return SalientFrames(*(np.concatenate([getattr(p, f) for p in parts]) for f in SalientFrames._fields))


def save_frames(frames: SalientFrames, path) -> None:
    """Write :class:`SalientFrames` to an ``.npz`` file (uncompressed, fast to read)."""
    np.savez(path, **frames._asdict())


def load_frames(path) -> SalientFrames:
    """Read a file written by :func:`save_frames`; errors name the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return SalientFrames(*(z[f] for f in SalientFrames._fields))
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"{path}: not a salient frames file ({type(e).__name__}: {e})") from None
