"""Tests for torchhand.data.noise (Kinect-v1-type structured-light depth noise)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torchhand.data.noise import _incidence_cos, apply_kinect_noise
from torchhand.data.noise_params import NOISE_MODELS, KinectNoise, noise_model

H, W = 480, 640
F = 525.0
K = torch.tensor([[F, 0.0, 319.5], [0.0, F, 239.5], [0.0, 0.0, 1.0]])
CENTRE = (slice(190, 290), slice(270, 370))  # 100 x 100 px around the principal point


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _frontal(z: float, batch: int = 1):
    depth = torch.full((batch, H, W), float(z))
    normals = torch.zeros(batch, H, W, 3)
    normals[..., 2] = -1.0
    return depth, normals


def _tilted_about_x(z0: float, tilt_deg: float):
    """Plane through (0, 0, z0) whose normal is tilted by ``tilt_deg`` about the camera's x axis."""
    a = math.radians(tilt_deg)
    v = torch.arange(H, dtype=torch.float32).view(H, 1).expand(H, W)
    ry = (v - K[1, 2]) / F
    denom = 1.0 + math.tan(a) * ry
    depth = torch.where(denom > 0.05, z0 / denom.clamp_min(0.05), torch.zeros_like(denom))
    normals = torch.zeros(H, W, 3)
    normals[..., 1] = -math.sin(a)
    normals[..., 2] = -math.cos(a)
    return depth[None], normals[None]


def _box_on_wall(z_box: float = 600.0, z_wall: float = 1000.0):
    depth, normals = _frontal(z_wall)
    depth[:, 200:280, 280:360] = z_box
    return depth, normals


def _valid_fraction(x: torch.Tensor) -> float:
    return (x > 0).float().mean().item()


# --------------------------------------------------------------------------- axial noise


def test_axial_std_and_mean_at_600mm():
    params = KinectNoise()
    depth, normals = _frontal(600.0)
    out = apply_kinect_noise(depth, normals, K, generator=_gen())
    crop = out[0][CENTRE]
    crop = crop[crop > 0]
    sigma = params.axial_sigma(600.0, 0.0)
    assert sigma == pytest.approx(1.2 + 1.9 * 0.2**2)
    assert abs(crop.mean().item() - 600.0) < 1.0
    assert crop.std().item() == pytest.approx(sigma, rel=0.3)


def test_axial_std_grows_with_depth():
    stds = {}
    for z in (600.0, 1200.0):
        depth, normals = _frontal(z)
        crop = apply_kinect_noise(depth, normals, K, generator=_gen())[0][CENTRE]
        crop = crop[crop > 0]
        stds[z] = crop.std().item()
        assert abs(crop.mean().item() - z) < 1.0
    assert stds[1200.0] > 1.5 * stds[600.0]
    assert stds[1200.0] == pytest.approx(KinectNoise().axial_sigma(1200.0), rel=0.3)


def test_axial_sigma_formula_terms():
    p = KinectNoise()
    # Nguyen et al. 2012 at 1 m: 1.2 + 1.9 * 0.6^2 mm, angle term 0.1 * (theta / (pi/2 - theta))^2.
    assert p.axial_sigma(1000.0) == pytest.approx(1.2 + 1.9 * 0.36)
    theta = math.radians(60)
    assert p.axial_sigma(1000.0, theta) == pytest.approx(1.2 + 1.9 * 0.36 + 0.1 * (theta / (math.pi / 2 - theta)) ** 2)
    assert p.lateral_sigma_px(0.0) == pytest.approx(0.8)
    t = torch.tensor([0.0, theta])
    expected = torch.tensor([p.axial_sigma(1000.0), p.axial_sigma(1000.0, theta)])
    assert torch.allclose(p.axial_sigma(torch.tensor(1000.0), t), expected)


# --------------------------------------------------------------------------- quantisation


def test_disparity_quantisation_spacing_at_1000mm():
    params = KinectNoise()
    depth, normals = _frontal(1000.0)
    out = apply_kinect_noise(depth, normals, K, generator=_gen())
    values = torch.unique(out[0][CENTRE]).double()
    values = values[(values > 995.0) & (values < 1005.0)]
    assert len(values) >= 3
    gaps = values.diff()
    mid = 0.5 * (values[1:] + values[:-1])
    expected = mid**2 / (F * params.baseline_mm) / 8.0  # z^2 / (f b) * 1/8 px, ~3.17 mm at 1 m
    assert torch.allclose(gaps, expected, rtol=0.02)
    assert params.quantisation_step(1000.0, F) == pytest.approx(1e6 / (F * 75.0 * 8.0))
    # Every value is f b / (k / 8) for an integer k.
    k = F * params.baseline_mm * 8.0 / values
    assert torch.allclose(k, k.round(), atol=1e-2)


def test_quantisation_can_be_disabled():
    depth, normals = _frontal(1000.0)
    params = KinectNoise(disparity_resolution_px=0.0)
    out = apply_kinect_noise(depth, normals, K, params, generator=_gen())
    assert torch.unique(out[0][CENTRE]).numel() > 1000


# --------------------------------------------------------------------------- dropout


def test_grazing_plane_loses_most_pixels_frontal_keeps_them():
    depth, normals = _frontal(600.0)
    frontal = apply_kinect_noise(depth, normals, K, generator=_gen())
    assert _valid_fraction(frontal) > 0.95

    depth, normals = _tilted_about_x(600.0, 80.0)
    rows, cols = slice(220, 260), slice(280, 360)  # within ~2.5 deg of 80 deg incidence
    assert bool((depth[0, rows, cols] > 0).all())
    tilted = apply_kinect_noise(depth, normals, K, generator=_gen())
    assert _valid_fraction(tilted[0, rows, cols]) < 0.5
    # The same holds with the incidence angle estimated from the depth map.
    estimated = apply_kinect_noise(depth, None, K, generator=_gen())
    assert _valid_fraction(estimated[0, rows, cols]) < 0.5
    # A moderately tilted plane (45 deg) keeps nearly everything.
    depth, normals = _tilted_about_x(600.0, 45.0)
    moderate = apply_kinect_noise(depth, normals, K, generator=_gen())
    assert _valid_fraction(moderate[0, rows, cols]) > 0.95


def test_estimated_incidence_angle_matches_normals():
    depth, normals = _tilted_about_x(700.0, 60.0)
    valid = depth > 0
    cos_n = _incidence_cos(depth, valid, normals, K[None])
    cos_d = _incidence_cos(depth, valid, None, K[None])
    inner = valid.clone()
    inner[:, :5] = inner[:, -5:] = False
    inner[..., :5] = inner[..., -5:] = False
    err = torch.rad2deg(torch.acos(cos_n[inner].clamp(-1, 1)) - torch.acos(cos_d[inner].clamp(-1, 1))).abs()
    assert err.max().item() < 1.0
    assert torch.rad2deg(torch.acos(cos_n[0, 240, 320])).item() == pytest.approx(60.0, abs=0.1)


def test_sparse_frame_uses_the_right_geometry():
    # Only a patch of a plane tilted 55 deg about x is present (true incidence 44-50 deg);
    # the model then works on a crop, whose rays must still be the full image's (with the
    # crop's own principal point the incidence would read 76-80 deg).
    depth, normals = _tilted_about_x(700.0, 55.0)
    region = (slice(None), slice(300, 340), slice(330, 430))
    patch = torch.zeros_like(depth)
    patch[region] = depth[region]
    step = KinectNoise(
        grazing_start_deg=56.0, grazing_full_deg=56.5, shadows=False, holes_per_frame=0.0,
        lateral_sigma0_px=0.0, lateral_sigma_angle_px=0.0,
    )
    for n in (normals, None):
        out = apply_kinect_noise(patch, n, K, step, generator=_gen())
        assert _valid_fraction(out[0, 302:338, 332:428]) > 0.99
        assert bool((out[0, :, :320] == 0).all()) and bool((out[0, :290] == 0).all())
    # The same patch of a plane tilted 75 deg (incidence 64-69 deg) is dropped.
    steep, steep_n = _tilted_about_x(700.0, 75.0)
    patch = torch.zeros_like(steep)
    patch[region] = steep[region]
    out = apply_kinect_noise(patch, steep_n, K, step, generator=_gen())
    assert _valid_fraction(out[0, 302:338, 332:428]) < 0.01


def test_projector_shadow_on_one_side_of_box():
    params = KinectNoise()
    depth, normals = _box_on_wall(600.0, 1000.0)
    out = apply_kinect_noise(depth, normals, K, generator=_gen())
    rows = slice(210, 270)
    width = F * params.baseline_mm * (1 / 600.0 - 1 / 1000.0)  # 26.25 px of shadow
    left = out[0, rows, 280 - int(width) + 4 : 280 - 4]  # wall just left of the box
    right = out[0, rows, 360 + 4 : 360 + int(width) - 4]  # wall just right of the box
    assert _valid_fraction(left) < 0.02
    assert _valid_fraction(right) > 0.97
    # Beyond the shadow band the wall is measured again.
    assert _valid_fraction(out[0, rows, 280 - int(width) - 12 : 280 - int(width) - 4]) > 0.97
    # The box itself and its wall values are measured (no depth is invented).
    assert _valid_fraction(out[0, 210:270, 290:350]) > 0.97
    # With the projector on the left, the shadow moves to the right side.
    mirrored = apply_kinect_noise(depth, normals, K, KinectNoise(projector_on_right=False), generator=_gen())
    assert _valid_fraction(mirrored[0, rows, 360 + 4 : 360 + int(width) - 4]) < 0.02
    assert _valid_fraction(mirrored[0, rows, 280 - int(width) + 4 : 280 - 4]) > 0.97
    # Disabled shadows: both sides measured.
    no_shadow = apply_kinect_noise(depth, normals, K, KinectNoise(shadows=False), generator=_gen())
    assert _valid_fraction(no_shadow[0, rows, 280 - int(width) + 4 : 280 - 4]) > 0.97


def test_lateral_noise_takes_existing_values_only():
    # No axial noise, no quantisation: every output value must be one of the input depths.
    params = KinectNoise(
        axial_sigma0_mm=0.0,
        axial_sigma_quad_mm=0.0,
        axial_sigma_angle_mm=0.0,
        disparity_resolution_px=0.0,
        shadows=False,
    )
    depth, normals = _box_on_wall(600.0, 1000.0)
    out = apply_kinect_noise(depth, normals, K, params, generator=_gen())
    assert set(torch.unique(out).tolist()) <= {0.0, 600.0, 1000.0}
    # The box's edge is jagged: some wall pixels take the box's depth and vice versa.
    edge = out[0, 210:270, 355:365]
    assert bool((edge == 600.0).any()) and bool((edge == 1000.0).any())
    # With sigma_L = 0.8 px, a pixel k px from the edge crosses it with P(N > (k - 0.5) / 0.8):
    # 0.266, 0.030, 0.001 for k = 1, 2, 3 on either side, i.e. 0.099 of these 6 columns.
    changed = (out != depth)[0, 210:270, 357:363].float().mean().item()
    assert 0.05 < changed < 0.15


def test_random_holes_and_range_clipping():
    depth, normals = _frontal(600.0)
    params = KinectNoise(holes_per_frame=20.0, lateral_sigma0_px=0.0, lateral_sigma_angle_px=0.0)
    out = apply_kinect_noise(depth, normals, K, params, generator=_gen())
    missing = (out == 0).sum().item()
    assert 20 < missing < 20 * 3 * 30  # a few disks of radius 1-3 px (5-29 px each)
    none = apply_kinect_noise(depth, normals, K, dataclasses.replace(params, holes_per_frame=0.0), generator=_gen())
    assert bool((none > 0).all())
    for z in (300.0, 4500.0):
        d, n = _frontal(z)
        assert bool((apply_kinect_noise(d, n, K, generator=_gen()) == 0).all())


# --------------------------------------------------------------------------- determinism, edge cases


def test_same_seed_same_output_different_seed_differs():
    depth, normals = _box_on_wall()
    a = apply_kinect_noise(depth, normals, K, generator=_gen(7))
    b = apply_kinect_noise(depth, normals, K, generator=_gen(7))
    c = apply_kinect_noise(depth, normals, K, generator=_gen(8))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_empty_stays_empty_no_nan_and_output_format():
    empty = torch.zeros(2, H, W)
    out = apply_kinect_noise(empty, torch.zeros(2, H, W, 3), K, generator=_gen())
    assert out.shape == (2, H, W) and out.dtype == torch.float32
    assert bool((out == 0).all())
    assert bool((apply_kinect_noise(empty, None, K, generator=_gen()) == 0).all())

    # A messy scene: box, grazing plane, empty background, batch with per-frame K, float64 input.
    box, box_n = _box_on_wall()
    box[:, :, :100] = 0
    tilt, tilt_n = _tilted_about_x(600.0, 85.0)
    depth = torch.cat([box, tilt]).double()
    normals = torch.cat([box_n, tilt_n])
    Ks = torch.stack([K, K * torch.tensor([[1.1], [1.1], [1.0]])])
    out = apply_kinect_noise(depth, normals, Ks, generator=_gen())
    assert out.dtype == torch.float32 and bool(torch.isfinite(out).all()) and bool((out >= 0).all())
    assert bool((out[0, :, :95] == 0).all())  # background stays empty away from the edge
    out = apply_kinect_noise(depth, None, Ks, generator=_gen())
    assert bool(torch.isfinite(out).all())
    assert depth.dtype == torch.float64  # input untouched
    assert apply_kinect_noise(torch.zeros(0, H, W), None, K).shape == (0, H, W)
    # Non-contiguous input is fine.
    transposed = torch.full((1, W, H), 800.0).transpose(1, 2)
    assert _valid_fraction(apply_kinect_noise(transposed, None, K, generator=_gen())) > 0.95


def test_wrong_inputs_raise_naming_the_argument():
    depth, normals = _frontal(600.0)
    with pytest.raises(ValueError, match="depth"):
        apply_kinect_noise(depth[0], normals, K)
    with pytest.raises(TypeError, match="depth"):
        apply_kinect_noise(depth.to(torch.int32), normals, K)
    with pytest.raises(TypeError, match="depth"):
        apply_kinect_noise(depth.numpy(), normals, K)
    with pytest.raises(ValueError, match="normals"):
        apply_kinect_noise(depth, normals[..., :2], K)
    with pytest.raises(ValueError, match="normals"):
        apply_kinect_noise(depth, normals[0], K)
    with pytest.raises(ValueError, match="K"):
        apply_kinect_noise(depth, normals, torch.eye(4))
    with pytest.raises(ValueError, match="K"):
        apply_kinect_noise(depth, normals, K.expand(3, 3, 3))
    with pytest.raises(TypeError, match="params"):
        apply_kinect_noise(depth, normals, K, params="kinect")
    with pytest.raises(TypeError, match="generator"):
        apply_kinect_noise(depth, normals, K, generator=0)
    bad = depth.clone()
    bad[0, 10, 10] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        apply_kinect_noise(bad, normals, K)
    bad[0, 10, 10] = -5.0
    with pytest.raises(ValueError, match="negative"):
        apply_kinect_noise(bad, normals, K)
    bad_n = normals.clone()
    bad_n[0, 1, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="normals"):
        apply_kinect_noise(depth, bad_n, K)


def test_params_validation_and_registry():
    with pytest.raises(ValueError, match="baseline_mm"):
        KinectNoise(baseline_mm=-1.0)
    with pytest.raises(ValueError, match="max_depth_mm"):
        KinectNoise(min_depth_mm=500.0, max_depth_mm=400.0)
    with pytest.raises(ValueError, match="hole_radius"):
        KinectNoise(hole_radius_min_px=3, hole_radius_max_px=1)
    with pytest.raises(ValueError, match="grazing_full_deg"):
        KinectNoise(grazing_start_deg=80.0, grazing_full_deg=70.0)
    assert noise_model("none") is None
    assert noise_model("kinect") == KinectNoise()
    assert set(NOISE_MODELS) == {"none", "kinect"}
    with pytest.raises(ValueError, match="kinect") as info:
        noise_model("kinect2")
    assert "none" in str(info.value)


def test_with_rendered_sphere():
    trimesh = pytest.importorskip("trimesh")
    from torchhand.geometry.camera import kinect_camera
    from torchhand.geometry.render import render

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=60.0)
    vertices = torch.tensor(mesh.vertices, dtype=torch.float32) + torch.tensor([0.0, 0.0, 700.0])
    camera = kinect_camera()
    result = render(vertices, torch.tensor(mesh.faces, dtype=torch.int64), camera)
    out = apply_kinect_noise(result.depth, result.normals, camera.K, generator=_gen())
    clean = result.depth > 0
    assert bool(torch.isfinite(out).all())
    kept = ((out > 0) & clean).sum().item() / clean.sum().item()
    assert 0.8 < kept < 1.0  # the rim (grazing incidence) is lost
    assert ((out > 0) & ~clean).sum().item() < 0.02 * clean.sum().item()  # only edge jitter outside
    diff = (out - result.depth)[(out > 0) & clean]
    assert diff.abs().median().item() < 3.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu_with_cpu_generator():
    depth, normals = _box_on_wall()
    cpu = apply_kinect_noise(depth, normals, K, generator=_gen(3))
    gpu = apply_kinect_noise(depth.cuda(), normals.cuda(), K.cuda(), generator=_gen(3))
    assert gpu.device.type == "cuda"
    same = (gpu.cpu() - cpu).abs() < 1e-3
    assert same.float().mean().item() > 0.999
