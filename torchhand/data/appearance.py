"""The colour appearance of rendered scenes, for trackers that read colour images
(Ballan et al. 2012: edges, optical flow and finger-nail salient points in 8 colour
views).

- **Colours**: skin for hands, the thesis objects' colours (:data:`MODEL_COLOURS`);
  finger **nails** (:func:`nail_faces`) as a paler patch on the back of each fingertip,
  the salient points of Ballan et al. Sec. 4.1.
- **Smooth shading** (:func:`shade`): the posed vertex normals interpolated with the
  render's barycentrics, turned towards the camera, lit by two lights fixed in the world
  (a key light from above and in front of camera 0, a weaker fill from below and behind)
  plus ambient light, so that a surface keeps its brightness from frame to frame as
  optical flow assumes, and every view sees shading.
- **A textured background** (:func:`background_texture`): smooth colour blobs and a
  few straight-edged shapes, fixed per camera over the sequence (a static room), so
  that edge and flow terms meet clutter as on real images.

Where a nail is: :func:`torchhand.model.fingertips.nail_faces` (the back of each
fingertip, read off the kinematics).
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from torchhand.geometry.camera import Camera
from torchhand.geometry.mesh import vertex_normals
from torchhand.geometry.render import RenderResult
from torchhand.model.fingertips import nail_faces
from torchhand.model.scene import Scene

__all__ = ["MODEL_COLOURS", "SKIN", "NAIL", "model_albedo", "face_albedo", "background_texture", "shade", "LIGHTS"]

#: RGB albedo (0..1) per model kind: skin for hands, the thesis objects' colours.
SKIN = (0.87, 0.67, 0.55)
NAIL = (0.98, 0.90, 0.88)
MODEL_COLOURS: Dict[str, tuple] = {"hand": SKIN, "ball": (0.85, 0.2, 0.15), "cube": (0.2, 0.45, 0.85),
                                   "pipe": (0.55, 0.55, 0.55), "rope": (0.2, 0.7, 0.3)}
_OTHER = (0.7, 0.7, 0.7)

#: (direction towards the light in world coordinates, intensity); camera 0's frame:
#: x right, y down, z forward, so (0.3, -0.6, -0.75) is above, in front and to the right.
LIGHTS = (((0.3, -0.6, -0.75), 0.75), ((-0.4, 0.5, 0.75), 0.3))
AMBIENT = 0.25


def _kind(model) -> str:
    return "hand" if model.kind != "object" else model.name


def model_albedo(scene: Scene) -> torch.Tensor:
    """(M, 3) float32 albedo per model of the scene (:data:`MODEL_COLOURS`, grey else)."""
    return torch.tensor([MODEL_COLOURS.get(_kind(m.assets), _OTHER) for m in scene.models], dtype=torch.float32)


def face_albedo(scene: Scene, nails: bool = True) -> torch.Tensor:
    """(F, 3) float32 albedo per face: the model's colour, :data:`NAIL` on the nails."""
    alb = model_albedo(scene)[scene.face_model_id.cpu()]
    if nails:
        alb[nail_faces(scene)] = torch.tensor(NAIL)
    return alb


def background_texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1]: a static, cluttered background (module docstring),
    the same for the same seed."""
    g = np.random.default_rng(seed)

    def field(cells: int, channels: int) -> np.ndarray:
        small = g.uniform(-1, 1, (cells, max(int(cells * width / height), 1), channels)).astype(np.float32)
        return cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC).reshape(height, width, channels)

    # brightness blobs at three scales, a little colour, on a muted base colour
    img = sum(amp * field(cells, 1) for cells, amp in ((4, 0.18), (12, 0.1), (40, 0.05)))
    img = img + 0.06 * field(6, 3) + np.asarray(g.uniform(0.35, 0.55, 3), np.float32)
    for _ in range(12):  # straight edges: boxes and bars of other colours
        x0, y0 = int(g.integers(0, width)), int(g.integers(0, height))
        w, h = int(g.integers(20, width // 3)), int(g.integers(10, height // 3))
        col = tuple(float(c) for c in g.uniform(0.2, 0.7) + g.uniform(-0.12, 0.12, 3))
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), col, thickness=-1 if g.uniform() < 0.6 else 3)
    return np.clip(img, 0, 1).astype(np.float32)


def shade(result: RenderResult, vertices: torch.Tensor, faces: torch.Tensor, albedo: torch.Tensor, camera: Camera,
          background: Optional[torch.Tensor] = None, lights: Sequence = LIGHTS, ambient: float = AMBIENT) -> torch.Tensor:
    """Colour images of one camera's render.

    Args:
        result: the render of ``vertices`` by ``camera`` ((B, H, W) fields).
        vertices: (B, V, 3) posed vertices, world mm; faces: (F, 3).
        albedo: (F, 3) per-face colour in [0, 1] (:func:`face_albedo`).
        background: (H, W, 3) in [0, 1] where nothing is hit (grey when None).
    Returns:
        (B, H, W, 3) uint8 RGB.
    """
    dev = vertices.device
    hit = result.face_id >= 0
    b, yy, xx = hit.nonzero(as_tuple=True)  # only the pixels that see a face are lit
    fid = result.face_id[b, yy, xx]
    vn = vertex_normals(vertices, faces.to(dev))  # (B, V, 3) world
    corners = faces.to(dev)[fid]  # (N, 3)
    nc = vn[b[:, None], corners]  # (N, 3 corners, 3)
    bary = result.barycentric[b, yy, xx].to(nc)
    u, v = bary[:, 0:1], bary[:, 1:2]
    n = F.normalize((1 - u - v) * nc[:, 0] + u * nc[:, 1] + v * nc[:, 2], dim=-1)
    # towards the camera: the hit point seen from the camera centre
    pc = vertices[b[:, None], corners]
    p = (1 - u - v) * pc[:, 0] + u * pc[:, 1] + v * pc[:, 2]
    view = p - camera.centre.to(p)
    n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)
    light = torch.full(n.shape[:-1], float(ambient), dtype=n.dtype, device=dev)
    for direction, intensity in lights:
        d = F.normalize(torch.as_tensor(direction, dtype=n.dtype, device=dev), dim=0)
        light = light + float(intensity) * (n @ d).clamp_min(0)
    shape = (*hit.shape, 3)
    rgb = (torch.full(shape, 0.25, dtype=n.dtype, device=dev) if background is None
           else background.to(n).expand(shape).clone())
    rgb[b, yy, xx] = albedo.to(n)[fid] * light[:, None]
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8)
