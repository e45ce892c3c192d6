"""An active-stereo depth sensor (RealSense D4xx / SR30x style), independent of the
Kinect model of :mod:`torchhand.data.noise`.

The hand localiser is trained on renders degraded by the project's Kinect model and
tested on renders degraded by this one, so that a test number does not reward
learning one noise model's quirks. It shares no code or parameters with the Kinect
model; its effects are those of a stereo matcher rather than of a speckle projector:

1. **range**: depth beyond ``far_mm`` (the projector's reach, 0.8-2 m on these
   sensors) or nearer than ``near_mm`` is invalid (0);
2. **occlusion holes**: a pixel whose surface the second camera (``baseline_mm`` to
   the right) cannot see is invalid; it is approximated by the pixels left of a depth
   step, over the step's disparity difference;
3. **flying pixels**: at depth steps a share ``flying`` of the edge pixels take a depth
   between the two sides (the matching window straddles the edge);
4. **matching noise**: Gaussian disparity noise of ``disparity_sigma_px``, then
   smoothing by the 3x3 matching window inside smooth regions, then quantisation of
   the disparity to ``subpixel`` px;
5. **dropout**: a Poisson number of irregular hole blobs (low texture, specularities).

All steps are vectorised over the batch; random numbers come from ``generator``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from torchhand.core.check import check_tensor

__all__ = ["StereoNoise", "apply_stereo_noise"]


@dataclass(frozen=True)
class StereoNoise:
    """Parameters of :func:`apply_stereo_noise` (defaults: a RealSense D415-like sensor
    at 640x480). ``far_mm`` may be a range: each frame then draws its own cut-off."""

    baseline_mm: float = 55.0
    near_mm: float = 160.0
    far_mm: tuple = (800.0, 2000.0)
    disparity_sigma_px: float = 0.08
    subpixel: float = 1.0 / 16.0
    edge_jump_mm: float = 25.0
    flying: float = 0.4
    holes_per_frame: float = 4.0
    hole_radius_px: tuple = (2.0, 9.0)


def _edges(z: torch.Tensor, jump: float) -> tuple:
    """(B, H, W) depth -> (step to the right is a far-to-near edge, any step) masks."""
    valid = z > 0
    zr = F.pad(z, (0, 1), value=0.0)[..., 1:]
    zd = F.pad(z, (0, 0, 0, 1), value=0.0)[..., 1:, :]
    step_r = valid & (zr > 0) & ((z - zr).abs() > jump)
    step_d = valid & (zd > 0) & ((z - zd).abs() > jump)
    near_right = step_r & (zr < z)  # this pixel is background, its right neighbour foreground
    return near_right, step_r | step_d


def apply_stereo_noise(depth: torch.Tensor, K: torch.Tensor, params: StereoNoise = StereoNoise(),
                       generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Clean (B, H, W) depth (mm, 0 = nothing) -> active-stereo-like depth (module doc).

    ``K``: (3, 3) or (B, 3, 3) intrinsics (``fx`` sets the disparity). Random draws are
    made on the CPU generator and moved to the depth's device.
    """
    check_tensor(depth, "depth", (None, None, None), spec="(B, H, W)")
    B, H, W = depth.shape
    dev = depth.device
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    fx = (K[..., 0, 0] if K.ndim == 3 else K[0, 0].expand(B)).to(dev, torch.float32).reshape(B, 1, 1)
    z = depth.to(torch.float32).clone()
    lo, hi = (params.far_mm, params.far_mm) if isinstance(params.far_mm, (int, float)) else params.far_mm
    far = (lo + (hi - lo) * torch.rand(B, generator=g)).to(dev).reshape(B, 1, 1)
    z = torch.where((z > far) | (z < params.near_mm), torch.zeros_like(z), z)

    # occlusion holes: background pixels left of a far-to-near step, over the disparity gap
    near_right, edge = _edges(z, params.edge_jump_mm)
    zr = F.pad(z, (0, 1), value=0.0)[..., 1:]
    gap = torch.where(near_right, fx * params.baseline_mm * (1.0 / zr.clamp_min(1.0) - 1.0 / z.clamp_min(1.0)),
                      torch.zeros_like(z)).clamp(0, 24)
    # spread each step's gap leftwards: a pixel is hidden if a step within `gap` px to its right
    hidden = torch.zeros_like(z, dtype=torch.bool)
    for s in range(0, 24):
        shifted = F.pad(gap, (0, s), value=0.0)[..., s:]
        hidden |= shifted > s
    z = torch.where(hidden, torch.zeros_like(z), z)

    # flying pixels: a share of the edge pixels takes a depth between its neighbours
    pad = F.pad(z[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    neigh = torch.stack([pad[:, 1:-1, 2:], pad[:, 1:-1, :-2], pad[:, 2:, 1:-1], pad[:, :-2, 1:-1]], 0)
    other = torch.where((neigh - z).abs() > params.edge_jump_mm, neigh, z).amax(0)
    fly = edge & (torch.rand(B, H, W, generator=g).to(dev) < params.flying) & (other > 0)
    t = torch.rand(B, H, W, generator=g).to(dev)
    z = torch.where(fly, z + t * (other - z), z)

    # matching noise in disparity, the 3x3 window on smooth regions, quantisation
    valid = z > 0
    disp = torch.where(valid, fx * params.baseline_mm / z.clamp_min(1.0), torch.zeros_like(z))
    disp = disp + params.disparity_sigma_px * torch.randn(B, H, W, generator=g).to(dev) * valid
    num = F.avg_pool2d((disp * valid)[:, None], 3, 1, 1)[:, 0]
    den = F.avg_pool2d(valid.float()[:, None], 3, 1, 1)[:, 0].clamp_min(1e-6)
    mean = num / den
    smooth = valid & ((mean - disp).abs() < 0.5)
    disp = torch.where(smooth, mean, disp)
    disp = torch.round(disp / params.subpixel) * params.subpixel
    z = torch.where(valid & (disp > 0), fx * params.baseline_mm / disp.clamp_min(1e-6), torch.zeros_like(z))

    # dropout blobs
    n = torch.poisson(torch.full((B,), params.holes_per_frame), generator=g).long()
    rows = torch.arange(H, device=dev).view(1, H, 1)
    cols = torch.arange(W, device=dev).view(1, 1, W)
    for k in range(int(n.max()) if B else 0):
        on = (n > k).to(dev).view(B, 1, 1)
        r = params.hole_radius_px[0] + (params.hole_radius_px[1] - params.hole_radius_px[0]) * torch.rand(B, generator=g)
        cu, cv = torch.rand(B, generator=g) * W, torch.rand(B, generator=g) * H
        ax = 0.5 + torch.rand(B, generator=g)
        d2 = ((cols - cu.to(dev).view(B, 1, 1)) * ax.to(dev).view(B, 1, 1)) ** 2 + (rows - cv.to(dev).view(B, 1, 1)) ** 2
        z = torch.where(on & (d2 < (r.to(dev) ** 2).view(B, 1, 1)), torch.zeros_like(z), z)
    return z
