"""Structured-light (Kinect v1 / Primesense Carmine) depth-sensor noise.

Turns clean ray-cast depth (:func:`torchhand.geometry.render.render`) into sensor-like depth:
lateral jitter, axial noise growing with depth squared and with the incidence angle,
disparity quantisation, projector shadows beside occluding edges, dropout at grazing
angles, a few small random holes and range clipping. The model, its parameters and
their sources are described in ``docs/noise.md``; the parameters are
:class:`torchhand.data.noise_params.KinectNoise`.

All steps are vectorised torch operations on the input's device (no OpenCV, no Python
loops over pixels or frames). Random numbers are drawn on the device of ``generator``
and copied to the input's device, so a seeded CPU generator makes the output
reproducible for inputs on any device.

Units are millimetres; the camera frame is x right, y down, z forward (OpenCV); pixel
centres are at integer coordinates.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional

import torch

from torchhand.data.noise_params import _MAX_ANGLE, KinectNoise

__all__ = ["apply_kinect_noise"]


# --------------------------------------------------------------------------- validation


def _fmt(shape) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ")"


def _check_inputs(depth, normals, K, params, generator) -> None:
    if not isinstance(depth, torch.Tensor):
        raise TypeError(f"depth must be a torch.Tensor of shape (B, H, W), got {type(depth).__name__}")
    if depth.ndim != 3:
        raise ValueError(f"depth must have shape (B, H, W), got {_fmt(depth.shape)}")
    if not depth.is_floating_point():
        raise TypeError(f"depth must have a floating point dtype (float32 mm), got {depth.dtype}; use depth.float()")
    B, H, W = depth.shape
    if normals is not None:
        if not isinstance(normals, torch.Tensor):
            raise TypeError(
                f"normals must be a torch.Tensor of shape (B, H, W, 3) or None, got {type(normals).__name__}"
            )
        if tuple(normals.shape) != (B, H, W, 3):
            raise ValueError(f"normals must have shape (B, H, W, 3) = {_fmt((B, H, W, 3))}, got {_fmt(normals.shape)}")
        if not normals.is_floating_point():
            raise TypeError(f"normals must have a floating point dtype, got {normals.dtype}")
        if normals.device != depth.device:
            raise ValueError(f"normals is on {normals.device} but depth is on {depth.device}; they must match")
    if not isinstance(K, torch.Tensor):
        raise TypeError(f"K must be a torch.Tensor of shape (3, 3) or (B, 3, 3), got {type(K).__name__}")
    if not (tuple(K.shape) == (3, 3) or (K.ndim == 3 and tuple(K.shape[1:]) == (3, 3) and K.shape[0] in (1, B))):
        raise ValueError(f"K must have shape (3, 3) or (B, 3, 3) with B={B}, got {_fmt(K.shape)}")
    if not K.is_floating_point():
        raise TypeError(f"K must have a floating point dtype, got {K.dtype}")
    if not isinstance(params, KinectNoise):
        raise TypeError(f"params must be a KinectNoise, got {type(params).__name__}")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
    # Value checks: one reduction each (NaN propagates through min/sum).
    if depth.numel():
        lo, hi = torch.aminmax(depth.detach())
        lo, hi = float(lo), float(hi)
        if math.isnan(lo) or math.isnan(hi) or math.isinf(hi):
            raise ValueError("depth contains NaN or inf; use 0 for missing pixels")
        if lo < 0:
            raise ValueError(f"depth contains negative values (min {lo}); use 0 for missing pixels")
    if normals is not None and normals.numel():
        # A float32 sum is finite iff all entries are (barring overflow: then check exactly).
        if not math.isfinite(float(normals.detach().sum())) and not bool(torch.isfinite(normals).all()):
            raise ValueError("normals contains NaN or inf")
    if not bool(torch.isfinite(K).all()):
        raise ValueError("K contains NaN or inf")
    Kd = K.detach().reshape(-1, 3, 3)
    if bool((Kd[:, 0, 0] <= 0).any()) or bool((Kd[:, 1, 1] <= 0).any()):
        raise ValueError("K must have positive focal lengths fx = K[..., 0, 0] and fy = K[..., 1, 1]")


# --------------------------------------------------------------------------- pieces


def _rays(K: torch.Tensor, H: int, W: int):
    """Viewing rays ``(x, y, 1)`` of the pixel centres: (B|1, H|1, W) x and (B|1, H, 1) y,
    and ``1 / |(x, y, 1)|`` (B|1, H, W). Cached for single (3, 3) cameras."""
    if K.shape[0] == 1:
        return _rays_cached(tuple(K.flatten().tolist()), H, W, str(K.device))
    return _rays_uncached(K, H, W)


@functools.lru_cache(maxsize=8)
def _rays_cached(K_flat, H, W, device):
    return _rays_uncached(torch.tensor(K_flat, dtype=torch.float32, device=device).view(1, 3, 3), H, W)


def _rays_uncached(K, H, W):
    dev, dt = K.device, K.dtype
    fx, fy, s = K[:, 0, 0].view(-1, 1, 1), K[:, 1, 1].view(-1, 1, 1), K[:, 0, 1].view(-1, 1, 1)
    cx, cy = K[:, 0, 2].view(-1, 1, 1), K[:, 1, 2].view(-1, 1, 1)
    v = torch.arange(H, device=dev, dtype=dt).view(1, H, 1)
    u = torch.arange(W, device=dev, dtype=dt).view(1, 1, W)
    ry = (v - cy) / fy
    rx = (u - cx) / fx if not bool((s != 0).any()) else (u - cx - s * ry) / fx
    return rx, ry, torch.rsqrt(rx * rx + ry * ry + 1.0)


def _incidence_cos(depth, valid, normals, K):
    """(B, H, W) cosine of the angle between the surface normal and the viewing ray.

    Values on empty pixels are finite but meaningless. Zero normals give 0 (grazing).
    With ``normals`` None the angle is estimated from the depth map: for a surface
    ``z(u, v)`` seen through a pinhole with zero skew, ``n ~ (-fx z_u, -fy z_v,
    fx z_u x + fy z_v y + z)`` with ``(x, y, 1)`` the pixel's viewing ray, so
    ``cos(angle) = z / (|n| |ray|)``. The derivatives ``z_u, z_v`` are one-sided
    differences, taking per pixel the side with the smaller jump among valid
    neighbours (so depth discontinuities do not read as grazing surfaces).
    """
    B, H, W = depth.shape
    rx, ry, inv_ray = _rays(K, H, W)
    if normals is not None:
        n = normals.to(depth.dtype)
        n0, n1, n2 = n[..., 0], n[..., 1], n[..., 2]
        dot = torch.addcmul(torch.addcmul(n2, n0, rx), n1, ry)
        nsq = torch.addcmul(torch.addcmul(n0 * n0, n1, n1), n2, n2)
        return dot.abs_().mul_(nsq.clamp_min_(1e-30).rsqrt_()).mul_(inv_ray)
    fx, fy = K[:, 0, 0].view(-1, 1, 1), K[:, 1, 1].view(-1, 1, 1)
    a = _one_sided_derivative(depth, valid, dim=2).mul_(fx)
    c = _one_sided_derivative(depth, valid, dim=1).mul_(fy)
    nz = torch.addcmul(torch.addcmul(depth, a, rx), c, ry)
    nsq = torch.addcmul(torch.addcmul(a * a, c, c), nz, nz)
    return (depth * inv_ray).mul_(nsq.clamp_min_(1e-30).rsqrt_())


def _one_sided_derivative(depth, valid, dim):
    """Forward or backward difference along ``dim``, whichever is smaller; 0 if neither is valid."""
    n = depth.shape[dim]
    if n < 2:
        return torch.zeros_like(depth)
    d = depth.diff(dim=dim)  # d[i] = z[i+1] - z[i]
    ok = valid.narrow(dim, 1, n - 1) & valid.narrow(dim, 0, n - 1)
    d = torch.where(ok, d, float("inf"))
    pad_shape = list(depth.shape)
    pad_shape[dim] = 1
    pad = torch.full(pad_shape, float("inf"), dtype=depth.dtype, device=depth.device)
    fwd = torch.cat([d, pad], dim=dim)
    bwd = torch.cat([pad, d], dim=dim)
    out = torch.where(fwd.abs() <= bwd.abs(), fwd, bwd)
    return torch.nan_to_num_(out, posinf=0.0, neginf=0.0)


def _projector_shadow(depth, fx, params):
    """(B, H, W) bool: pixels the camera sees but the projector does not (meaningless where empty).

    With the projector at ``+x`` (baseline ``b``) and disparity ``D(u) = f b / z(u)``
    in image pixels, a point seen at column ``u`` lies on the projector ray with
    coordinate ``p(u) = u - D(u)``; along an image row (an epipolar line) it is
    occluded from the projector iff a nearer surface to its right crosses that ray,
    i.e. ``min_{u' > u} p(u') < p(u)``. This is a suffix minimum per row
    (``torch.cummin`` on the flipped row). The shadow therefore is a band on the left
    of an occluding edge, ``f b (1/z_near - 1/z_far)`` px wide (at most ``f b / z_far``),
    and surfaces tilted away from the projector so steeply that ``p`` decreases are
    self-shadowed. Empty pixels (depth 0) count as infinitely far and never occlude.
    With the projector on the left the image is mirrored.
    """
    if not params.projector_on_right:
        return _projector_shadow(depth.flip(-1), fx, dataclasses.replace(params, projector_on_right=True)).flip(-1)
    W = depth.shape[-1]
    disparity = torch.nan_to_num_(torch.div(fx * params.baseline_mm, depth), posinf=0.0)  # 0 where empty
    p = torch.arange(W, device=depth.device, dtype=depth.dtype) - disparity
    suffix = p.flip(-1).cummin(dim=-1).values.flip(-1)  # min over u' >= u
    shadow = torch.zeros_like(depth, dtype=torch.bool)
    torch.lt(suffix[..., 1:], p[..., :-1].sub_(params.shadow_tolerance_px), out=shadow[..., :-1])
    return shadow


def _box_max(x, R):
    """Max over the (2R+1)^2 window around each pixel of (..., H, W) ``x`` (-inf outside)."""
    L = 2 * R + 1
    for dim, pad in ((-1, (R, R)), (-2, (0, 0, R, R))):
        y = torch.nn.functional.pad(x, pad, value=float("-inf"))
        span = 1
        while span < L:  # doubling: after each step y[i] = max(x[i - R .. i - R + span - 1])
            step = min(span, L - span)
            n = y.shape[dim] - step
            y = torch.maximum(y.narrow(dim, 0, n), y.narrow(dim, step, n))
            span += step
        x = y
    return x


def _lateral(z, ratio, params, generator):
    """Step 3 of :func:`apply_kinect_noise`: returns new ``(z, ratio)``.

    Only pixels whose (2R+1)^2 neighbourhood holds depths more than
    ``lateral_min_jump_mm`` apart can change, so the random shifts are drawn for those
    pixels only (all of them if the threshold is 0); shifts are clamped to R px.
    """
    B, H, W = z.shape
    R = _LATERAL_RADIUS_PX
    thr = params.lateral_min_jump_mm
    if thr > 0:
        both = _box_max(torch.stack([z, -z]), R)  # local max and -(local min)
        bvu = ((both[0] + both[1]) > thr).nonzero()
    else:
        grid = torch.meshgrid(*(torch.arange(n, device=z.device) for n in (B, H, W)), indexing="ij")
        bvu = torch.stack(grid, dim=-1).view(-1, 3)
    if bvu.shape[0] == 0:
        return z, ratio
    b, v, u = bvu.unbind(1)
    bh = b * H
    idx = (bh + v) * W + u
    rf = ratio.view(-1)
    sigma = rf.index_select(0, idx).mul_(params.lateral_sigma_angle_px).add_(params.lateral_sigma0_px)
    shift = _randn((2, idx.numel()), generator, z.device, z.dtype).mul_(sigma).round_().clamp_(-R, R).long()
    src = (bh + (v + shift[0]).clamp_(0, H - 1)) * W + (u + shift[1]).clamp_(0, W - 1)
    zf = z.reshape(-1)
    z_dst, z_src = zf.index_select(0, idx), zf.index_select(0, src)
    take = (z_src - z_dst).abs_() > thr if thr > 0 else torch.ones_like(z_dst, dtype=torch.bool)
    r_new = torch.where(take, rf.index_select(0, src), rf.index_select(0, idx))
    z = z.clone()  # may alias the caller's input
    z.view(-1).index_copy_(0, idx, torch.where(take, z_src, z_dst))
    rf.index_copy_(0, idx, r_new)
    return z, ratio


def _randn(shape, generator, device, dtype):
    if generator is None:
        return torch.randn(shape, device=device, dtype=dtype)
    return torch.randn(shape, generator=generator, device=generator.device, dtype=dtype).to(device)


def _rand(shape, generator, device, dtype):
    if generator is None:
        return torch.rand(shape, device=device, dtype=dtype)
    return torch.rand(shape, generator=generator, device=generator.device, dtype=dtype).to(device)


def _random_holes(B, H, W, params, generator, device):
    """Flat (B * H * W) indices of the pixels of a Poisson number of random disks per frame; None if none."""
    gdev = generator.device if generator is not None else torch.device(device)
    counts = torch.poisson(torch.full((B,), float(params.holes_per_frame), device=gdev), generator=generator)
    M = int(counts.max().item())
    if M == 0:
        return None
    r_lo, r_hi = params.hole_radius_min_px, params.hole_radius_max_px
    draws = _rand((B, M, 3), generator, device, torch.float32)
    cu = (draws[..., 0] * W).long().clamp_(0, W - 1)
    cv = (draws[..., 1] * H).long().clamp_(0, H - 1)
    radius = (draws[..., 2] * (r_hi - r_lo + 1)).long().clamp_(max=r_hi - r_lo) + r_lo
    offs = torch.arange(-r_hi, r_hi + 1, device=device)
    dv, du = torch.meshgrid(offs, offs, indexing="ij")
    du, dv = du.reshape(1, 1, -1), dv.reshape(1, 1, -1)
    uu, vv = cu[..., None] + du, cv[..., None] + dv
    keep = (du * du + dv * dv <= (radius * radius)[..., None]) & (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
    keep &= (torch.arange(M, device=device).view(1, M) < counts.to(device).view(B, 1))[..., None]
    flat = (torch.arange(B, device=device).view(B, 1, 1) * H + vv) * W + uu
    return flat[keep]


# --------------------------------------------------------------------------- public API


@torch.no_grad()
def apply_kinect_noise(
    depth: torch.Tensor,
    normals: Optional[torch.Tensor],
    K: torch.Tensor,
    params: KinectNoise = KinectNoise(),
    generator: Optional[torch.Generator] = None,
) -> torch.Tensor:
    """Clean depth -> Kinect-v1-like depth (see :class:`KinectNoise` and ``docs/noise.md``).

    Steps 1-6 run on the bounding box (over the batch) of the non-empty pixels, grown
    by 4 px; outside it nothing can change, so this only saves time on sparse frames
    (e.g. hands rendered without a background). Steps, in order, each vectorised over
    the batch and all pixels:

    1. incidence angle per pixel, from ``normals`` or estimated from ``depth``;
    2. surface points the sensor cannot measure are removed from the clean depth:
       projector shadows (exact per-row visibility test) and grazing-angle dropout
       (probability ramping linearly from ``grazing_start_deg`` to ``grazing_full_deg``);
    3. lateral noise: each pixel looks up the pixel at a random integer offset
       ``round(sigma_L(angle) * N(0, 1))`` per axis (clamped to 4 px, i.e. 4 ``sigma_L``
       at 75 degrees incidence, and to the image) and takes its depth if the two differ
       by more than ``lateral_min_jump_mm`` (i.e. across a depth edge or a hole), so
       edges and hole borders become jagged without new depth values being invented;
    4. axial Gaussian noise ``sigma_z(z, angle)``;
    5. disparity quantisation to ``disparity_resolution_px`` (``z = f b / d``);
    6. range clipping to ``[min_depth_mm, max_depth_mm]``;
    7. a Poisson number of random small disk-shaped holes per frame.

    Random numbers are drawn only where needed, in this order: dropout uniforms for the
    pixels beyond ``grazing_start_deg``; lateral normals (2, M) for the M pixels near a
    depth jump; axial normals for the (B, h, w) box above; hole counts (Poisson) and
    hole centres/radii. The stream therefore depends on the input, deterministically.

    Args:
        depth: (B, H, W) clean depth in mm (float), 0 where empty. Not modified.
        normals: (B, H, W, 3) camera-frame surface normals (any orientation, need not
            be unit), e.g. ``RenderResult.normals``; or None to estimate the incidence
            angle from ``depth`` (assumes zero skew in ``K``).
        K: (3, 3) or (B, 3, 3) intrinsics of the depth image.
        params: the noise parameters.
        generator: a seeded ``torch.Generator`` makes the output deterministic. Random
            numbers are drawn on the generator's device and copied to ``depth.device``,
            so a CPU generator works for inputs on any device. None uses torch's global
            RNG on ``depth.device``.

    Returns:
        (B, H, W) float32 depth in mm on ``depth.device``, 0 where no measurement.

    Raises:
        TypeError / ValueError: naming the offending argument for wrong types, shapes
        or dtypes, NaN/inf or negative depth, non-positive focal lengths.
    """
    _check_inputs(depth, normals, K, params, generator)
    B, H, W = depth.shape
    device = depth.device
    dt = torch.float32
    out = torch.zeros((B, H, W), dtype=dt, device=device)
    if depth.numel() == 0:
        return out
    z = depth.detach().to(dt)
    Kb = K.detach().to(device=device, dtype=dt).reshape(-1, 3, 3)
    box = _working_box(z)
    if box is None:
        return out
    v0, v1, u0, u1 = box
    if (v0, v1, u0, u1) != (0, H, 0, W):
        z = z[:, v0:v1, u0:u1]
        normals = None if normals is None else normals[:, v0:v1, u0:u1]
        Kb = Kb.clone()
        Kb[:, 0, 2] -= u0
        Kb[:, 1, 2] -= v0
    out[:, v0:v1, u0:u1] = _noise_core(z.contiguous(), normals, Kb, params, generator)

    # 7. random holes (over the whole image)
    if params.holes_per_frame > 0:
        holes = _random_holes(B, H, W, params, generator, device)
        if holes is not None:
            out.view(-1)[holes] = 0.0
    return out


#: Lateral shifts are clamped to this many pixels (about 4 sigma_L at 75 deg incidence,
#: 5.6 sigma_L at normal incidence). Also the margin of the working box.
_LATERAL_RADIUS_PX = 4


def _working_box(z):
    """``(v0, v1, u0, u1)``: the rows and columns of the bounding box of the non-empty
    pixels of ``z`` (B, H, W) over the batch, grown by :data:`_LATERAL_RADIUS_PX` and
    clipped to the image; None if every pixel is empty.

    Lateral shifts cannot cross that margin (they are clamped to it) and outside the box
    everything stays empty, so noise on the box is the same as on the full image, only
    faster for sparse frames.
    """
    B, H, W = z.shape
    rows = torch.nonzero(z.amax(dim=2).amax(dim=0) > 0).flatten()
    if rows.numel() == 0:
        return None
    cols = torch.nonzero(z.amax(dim=1).amax(dim=0) > 0).flatten()
    m = _LATERAL_RADIUS_PX
    v0, v1 = max(int(rows[0]) - m, 0), min(int(rows[-1]) + m + 1, H)
    u0, u1 = max(int(cols[0]) - m, 0), min(int(cols[-1]) + m + 1, W)
    return v0, v1, u0, u1


def _noise_core(z, normals, Kb, params, generator):
    """Steps 1-6 of :func:`apply_kinect_noise` on a (B, H, W) float32 contiguous crop.

    ``z`` may alias the caller's input: it is never modified in place.
    """
    B, H, W = z.shape
    device, dt = z.device, z.dtype
    fx = float(Kb[0, 0, 0]) if Kb.shape[0] == 1 else Kb[:, 0, 0].view(B, 1, 1)
    fb = (fx if params.focal_px is None else float(params.focal_px)) * params.baseline_mm
    nonempty = torch.sign(z)  # 1.0 / 0.0 (depth >= 0 was checked)

    # 1. incidence angle; both sigma formulas use ratio = theta / (pi/2 - theta), 0 where empty
    if normals is not None:
        cos = _incidence_cos(z, None, normals.detach(), Kb)
    else:
        cos = _incidence_cos(z, z > 0, None, Kb)
    angle = torch.acos_(cos.clamp_(0.0, 1.0))
    ratio = angle.clamp_max(_MAX_ANGLE)
    ratio = ratio.div_(ratio.neg().add_(math.pi / 2)).mul_(nonempty)

    # 2. unmeasurable surface points: projector shadow, grazing-angle dropout
    if params.shadows:
        z = z.masked_fill(_projector_shadow(z, fx, params), 0.0)
    if params.grazing_start_deg < 90.0:
        a0, a1 = math.radians(params.grazing_start_deg), math.radians(params.grazing_full_deg)
        r0 = a0 / (math.pi / 2 - a0)  # ratio is monotonic in the angle and 0 where empty
        cand = (ratio > r0).view(-1).nonzero().squeeze(1)  # uniforms only where p > 0
        if cand.numel():
            p_drop = angle.view(-1)[cand].sub_(a0).mul_(1.0 / (a1 - a0))
            dropped = cand[_rand(cand.shape, generator, device, dt) < p_drop]
            z = z.clone() if not params.shadows else z
            z.view(-1)[dropped] = 0.0

    # 3. lateral noise: nearest-neighbour lookup at a random integer offset
    if params.lateral_sigma0_px > 0 or params.lateral_sigma_angle_px > 0:
        z, ratio = _lateral(z, ratio, params, generator)
        nonempty = torch.sign(z)

    # 4. axial noise, the Gaussian's variance reduced by the quantisation's q^2 / 12
    res = params.disparity_resolution_px
    if params.axial_sigma0_mm > 0 or params.axial_sigma_quad_mm > 0 or params.axial_sigma_angle_mm > 0:
        sigma = (z - 1000.0 * params.axial_z0_m).square_().mul_(params.axial_sigma_quad_mm * 1e-6)
        sigma.add_(params.axial_sigma0_mm)
        if params.axial_sigma_angle_mm > 0:  # 0.1 mm sqrt(m) / sqrt(z [m]) = 0.1 sqrt(1000) / sqrt(z [mm])
            inv_sqrt_z = z.clamp_min(1.0).rsqrt_()
            sigma.addcmul_(ratio.square_(), inv_sqrt_z, value=params.axial_sigma_angle_mm * math.sqrt(1000.0))
        if res > 0 and params.compensate_quantisation:
            var = sigma.square_()
            z2 = z * z
            if isinstance(fb, float):
                q2 = z2.square_().mul_((res / fb) ** 2 / 12.0)
            else:
                q2 = (z2 * res / fb).square_() / 12.0
            sigma = torch.maximum(var - q2, var * 0.25).sqrt_()
        z = torch.addcmul(z, sigma.mul_(nonempty), _randn((B, H, W), generator, device, dt))  # empty stays 0

    # 5. disparity quantisation: k = round(d / res) disparity levels, z = f b / (k res)
    if res > 0:  # z = 0 stays 0 (d = inf); z < 0 stays < 0 or becomes inf: both dropped below
        z = torch.div(fb / res, torch.div(fb / res, z).round_())

    # 6. range clipping (empty pixels are 0 here, below any positive minimum)
    return torch.where((z >= max(params.min_depth_mm, 1e-3)) & (z <= params.max_depth_mm), z, 0.0)
