"""Tests for torchhand.geometry.camera."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from torchhand.geometry.image_ops import max_filter_3x3
from torchhand.geometry.camera import (
    Camera,
    PluckerRays,
    depth_to_normals,
    depth_to_points,
    depth_to_points_and_normals,
    kinect_camera,
    pixel_rays,
    point_to_ray_residual,
    project_points,
    transform_points,
    unproject_pixels,
)
from torchhand.geometry.camera_rig import CameraRig


def _rotation(axis: list[float], angle: float, dtype=torch.float64) -> torch.Tensor:
    rvec = np.asarray(axis, dtype=np.float64)
    rvec = rvec / np.linalg.norm(rvec) * angle
    return torch.tensor(cv2.Rodrigues(rvec)[0], dtype=dtype)


def _rigid(axis, angle, t, dtype=torch.float64) -> torch.Tensor:
    T = torch.eye(4, dtype=dtype)
    T[:3, :3] = _rotation(axis, angle, dtype)
    T[:3, 3] = torch.tensor(t, dtype=dtype)
    return T


def _K(dtype=torch.float64, skew=0.0) -> torch.Tensor:
    return torch.tensor([[525.0, skew, 319.5], [0.0, 530.0, 239.5], [0.0, 0.0, 1.0]], dtype=dtype)


def _random_points(gen, shape, dtype=torch.float64) -> torch.Tensor:
    p = torch.rand(*shape, 3, generator=gen, dtype=dtype) - 0.5
    return p * torch.tensor([400.0, 300.0, 400.0], dtype=dtype) + torch.tensor([0.0, 0.0, 700.0], dtype=dtype)


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(0)


# ------------------------------------------------------------------ pure functions


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_project_unproject_round_trip(gen, dtype):
    points = _random_points(gen, (2, 50), dtype)
    K = _K(dtype, skew=1.5)
    pixels = project_points(points, K)
    assert pixels.shape == (2, 50, 2) and pixels.dtype == dtype
    back = unproject_pixels(pixels, points[..., 2], K)
    tol = 1e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(back, points, atol=tol, rtol=0)


def test_project_points_matches_opencv(gen):
    points = _random_points(gen, (100,))
    K = _K()  # cv2.projectPoints ignores skew
    ours = project_points(points, K)
    ref, _ = cv2.projectPoints(points.numpy(), np.zeros(3), np.zeros(3), K.numpy(), None)
    np.testing.assert_allclose(ours.numpy(), ref[:, 0], atol=1e-8)


def test_project_broadcasts_leading_dims(gen):
    points = _random_points(gen, (3, 1, 7))  # (3, 1, N, 3)
    K = torch.stack([_K(), _K() * torch.tensor([[2.0, 1, 1], [1, 2, 1], [1, 1, 1]], dtype=torch.float64)])
    out = project_points(points, K)  # K (2, 3, 3) broadcasts against (3, 1)
    assert out.shape == (3, 2, 7, 2)
    torch.testing.assert_close(out[:, 0], project_points(points[:, 0], K[0]))


def test_transform_points_matches_homogeneous(gen):
    T = _rigid([1, 2, 3], 0.7, [10.0, -20.0, 30.0])
    points = _random_points(gen, (4, 9))
    homo = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    ref = (homo @ T.T)[..., :3]
    torch.testing.assert_close(transform_points(T, points), ref)


def _slow_depth_to_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    B, H, W = depth.shape
    out = np.zeros((B, H, W, 3))
    Kinv = np.linalg.inv(K)
    for b in range(B):
        for v in range(H):
            for u in range(W):
                z = depth[b, v, u]
                if z > 0:
                    out[b, v, u] = Kinv @ np.array([u, v, 1.0]) * z
    return out


def test_depth_to_points_matches_reference(gen):
    depth = torch.rand(2, 6, 7, generator=gen, dtype=torch.float64) * 1000 + 200
    depth[0, 1, 2] = 0.0
    depth[1, 5, 6] = 0.0
    K = torch.tensor([[50.0, 0.0, 3.2], [0.0, 55.0, 2.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    points = depth_to_points(depth, K)
    assert points.shape == (2, 6, 7, 3)
    np.testing.assert_allclose(points.numpy(), _slow_depth_to_points(depth.numpy(), K.numpy()), atol=1e-9)
    assert (points[0, 1, 2] == 0).all() and (points[1, 5, 6] == 0).all()
    # Batched K gives the same result.
    torch.testing.assert_close(depth_to_points(depth, K.expand(2, 3, 3)), points)


def test_depth_to_points_honours_skew():
    """Back-projected pixels project back onto themselves with a skewed camera."""
    K = _K(skew=1.5)
    depth = torch.full((1, 6, 8), 700.0, dtype=torch.float64)
    depth[0, 2, 3] = 650.0
    points = depth_to_points(depth, K)
    v, u = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    uv = project_points(points[0].reshape(-1, 3), K)
    torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(-1, 2).double(), rtol=0, atol=1e-9)


def test_points_and_normals_match_kornia(gen):
    """The shared back-projection gives depth_to_points and kornia's Sobel normals
    (flipped towards the camera, zero next to invalid pixels)."""
    import kornia.geometry.depth as kd

    depth = torch.rand(2, 20, 30, generator=gen, dtype=torch.float64) * 50 + 500
    depth[0, 4:8, 10:15] = 0.0
    depth[1, 12, 3] = float("nan")
    K = torch.tensor([[300.0, 0.0, 14.5], [0.0, 300.0, 9.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    points, normals = depth_to_points_and_normals(depth, K)
    torch.testing.assert_close(points, depth_to_points(depth, K), rtol=0, atol=0)
    torch.testing.assert_close(normals, depth_to_normals(depth, K), rtol=0, atol=0)
    clean = torch.where(depth > 0, depth, 0.0)
    ref = -kd.depth_to_normals(clean[:, None], K.expand(2, 3, 3)).permute(0, 2, 3, 1)
    bad = torch.nn.functional.max_pool2d((~(depth > 0))[:, None].double(), 3, 1, 1)[:, 0] > 0
    torch.testing.assert_close(normals[~bad], ref[~bad], rtol=0, atol=1e-12)
    assert (normals[bad] == 0).all() and bool(bad[0, 3:9, 9:16].all()) and bool(bad[1, 11:14, 2:5].all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opencv_points_and_normals_match_the_torch_backend(gen, dtype):
    """The host backend of preprocessing gives the torch backend's points exactly and
    its normals to float rounding, with the same zeros (invalid pixels, their 3x3
    neighbours, an image edge), for a skewed camera and batched intrinsics."""
    depth = (torch.rand(2, 20, 30, generator=gen, dtype=torch.float64) * 50 + 500).to(dtype)
    depth[0, 4:8, 10:15] = 0.0
    depth[1, 12, 3] = float("nan")
    depth[1, 0, 7] = 0.0
    K = torch.tensor([[[300.0, 2.0, 14.5], [0.0, 310.0, 9.5], [0.0, 0.0, 1.0]],
                      [[280.0, 0.0, 11.0], [0.0, 280.0, 8.0], [0.0, 0.0, 1.0]]], dtype=dtype)
    points, normals = depth_to_points_and_normals(depth, K)
    p, n = depth_to_points_and_normals(depth, K, backend="opencv")
    assert p.dtype == n.dtype == dtype and p.shape == n.shape == (2, 20, 30, 3)
    torch.testing.assert_close(p, points, rtol=0, atol=0)
    torch.testing.assert_close(n, normals, rtol=0, atol=1e-9 if dtype == torch.float64 else 5e-5)
    assert torch.equal(n.norm(dim=-1) == 0, normals.norm(dim=-1) == 0)
    with pytest.raises(ValueError, match="backend"):
        depth_to_points_and_normals(depth, K, backend="cuda")
    with pytest.raises(ValueError, match="float32 or float64"):
        depth_to_points_and_normals(depth.half(), K.half(), backend="opencv")


def test_max_filter_equals_max_pool(gen):
    x = torch.randn(3, 17, 23, generator=gen)
    x[0, 0, 0], x[1, 5, 5] = float("inf"), float("-inf")
    expected = torch.nn.functional.max_pool2d(x[:, None], 3, 1, 1)[:, 0]
    assert torch.equal(max_filter_3x3(x), expected)
    assert torch.equal(max_filter_3x3(x[:, :1, :1]), x[:, :1, :1])

def test_depth_to_normals_tilted_plane():
    # Plane z = 500 + 0.5 x (camera frame): normal (0.5, 0, -1)/|.| towards the camera.
    K = torch.tensor([[100.0, 0.0, 15.5], [0.0, 100.0, 11.5], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    xn = (u - 15.5) / 100.0
    depth = (500.0 / (1.0 - 0.5 * xn))[None]
    depth[0, 10, 10] = 0.0  # an invalid pixel poisons its 3x3 neighbourhood only
    normals = depth_to_normals(depth, K)
    assert normals.shape == (1, 24, 32, 3)
    expected = torch.tensor([0.5, 0.0, -1.0]) / math.sqrt(1.25)
    interior = normals[0, 1:-1, 1:-1].reshape(-1, 3)
    ok = interior.norm(dim=-1) > 0
    torch.testing.assert_close(interior[ok], expected.expand_as(interior[ok]), atol=1e-3, rtol=0)
    assert (normals[0, 9:12, 9:12] == 0).all()
    assert normals[0, 5, 5].norm() > 0.99


def test_plucker_residual_on_and_off_ray(gen):
    K = _K()
    T_cw = _rigid([0.3, -1, 0.2], 0.9, [40.0, -15.0, 250.0])
    size = torch.tensor([640.0, 480.0], dtype=torch.float64)
    pixels = torch.rand(3, 20, 2, generator=gen, dtype=torch.float64) * size
    rays = pixel_rays(pixels, K, T_cw)
    assert isinstance(rays, PluckerRays)
    assert rays.direction.shape == rays.moment.shape == (3, 20, 3)
    torch.testing.assert_close(rays.direction.norm(dim=-1), torch.ones(3, 20, dtype=torch.float64))

    centre = torch.linalg.inv(T_cw)[:3, 3]
    s = torch.rand(3, 20, 1, generator=gen, dtype=torch.float64) * 2000 - 500
    on_ray = centre + s * rays.direction
    torch.testing.assert_close(point_to_ray_residual(on_ray, rays), torch.zeros_like(on_ray), atol=1e-9, rtol=0)

    # Points on the ray project back to the pixel (those in front of the camera).
    in_front = centre + (s.abs() + 10) * rays.direction
    cam = Camera(K=K, T_cw=T_cw, width=640, height=480)
    torch.testing.assert_close(cam.project(in_front), pixels)

    off = _random_points(gen, (3, 20))
    residual = point_to_ray_residual(off, rays)
    diff = off - centre
    dist = (diff - (diff * rays.direction).sum(-1, keepdim=True) * rays.direction).norm(dim=-1)
    torch.testing.assert_close(residual.norm(dim=-1), dist, atol=1e-9, rtol=1e-9)


# ------------------------------------------------------------------ Camera


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_camera_extrinsics_round_trip(gen, dtype):
    T_cw = _rigid([1, 0.5, -0.2], 0.4, [30.0, -50.0, 100.0], dtype)
    cam = Camera.from_intrinsics(525, 525, 319.5, 239.5, 640, 480, T_cw=T_cw, dtype=dtype)
    assert cam.K.dtype == dtype and cam.T_cw.dtype == dtype
    world = transform_points(cam.T_wc, _random_points(gen, (2, 30), dtype))
    pixels = cam.project(world)
    z = cam.to_camera(world)[..., 2]
    back = transform_points(cam.T_wc, unproject_pixels(pixels, z, cam.K))
    tol = 2e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(back, world, atol=tol, rtol=0)
    torch.testing.assert_close(cam.T_wc @ cam.T_cw, torch.eye(4, dtype=dtype), atol=1e-6, rtol=0)
    torch.testing.assert_close(cam.centre, torch.linalg.inv(T_cw)[:3, 3], atol=1e-4, rtol=0)


def test_camera_backproject_matches_project():
    T_cw = _rigid([0, 1, 0], 0.3, [5.0, 0.0, 20.0])
    cam = Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, 32, 24, T_cw=T_cw, dtype=torch.float64)
    depth = torch.full((2, 24, 32), 400.0, dtype=torch.float64)
    depth[1] = 650.0
    depth[0, 0, 0] = 0.0
    world = cam.backproject(depth)
    assert world.shape == (2, 24, 32, 3)
    assert (world[0, 0, 0] == 0).all()
    v, u = torch.meshgrid(
        torch.arange(24.0, dtype=torch.float64), torch.arange(32.0, dtype=torch.float64), indexing="ij"
    )
    grid = torch.stack([u, v], -1).reshape(1, -1, 2)
    pixels = cam.project(world[1].reshape(1, -1, 3))
    torch.testing.assert_close(pixels, grid)


def test_camera_rays_pass_through_backprojected_points():
    cam = kinect_camera(_rigid([1, 1, 0], 0.2, [0.0, 10.0, -30.0], torch.float32))
    depth = torch.full((1, 480, 640), 800.0)
    world = cam.backproject(depth)
    pixels = torch.tensor([[[0.0, 0.0], [639.0, 479.0], [320.0, 100.0]]])
    rays = cam.rays(pixels)
    points = world[0, pixels[0, :, 1].long(), pixels[0, :, 0].long()][None]
    assert point_to_ray_residual(points, rays).norm(dim=-1).max() < 1e-2


def test_kinect_camera_and_dict_round_trip():
    cam = kinect_camera()
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (525.0, 525.0, 319.5, 239.5, 640, 480)
    torch.testing.assert_close(cam.T_cw, torch.eye(4))
    T = _rigid([0, 0, 1], 0.5, [1.0, 2.0, 3.0], torch.float32)
    cam2 = Camera.from_intrinsics(500, 510, 300, 200, 320, 240, T_cw=T, name="side")
    data = json.loads(json.dumps(cam2.to_dict()))
    back = Camera.from_dict(data)
    assert back.name == "side" and (back.width, back.height) == (320, 240)
    torch.testing.assert_close(back.K, cam2.K)
    torch.testing.assert_close(back.T_cw, cam2.T_cw)


def test_scaled_camera_agrees_with_cv2_resize(gen):
    """A camera ``scaled`` by s sees what cv2.resize by s makes of its image: a point
    projects to s (u + 1/2) - 1/2, the image's outer edges stay put."""
    cam = Camera(_K(), _rigid([0, 1, 0], 0.3, [10.0, -5.0, 20.0]), 640, 480)
    big = cam.scaled(2.5)
    assert (big.width, big.height) == (1600, 1200)
    pts = _random_points(gen, (1, 50))
    assert torch.allclose(big.project(pts), 2.5 * (cam.project(pts) + 0.5) - 0.5, atol=1e-9)
    # a white pixel at (u, v) = (100, 40), resized by an integer factor: the same place
    img = np.zeros((480, 640), np.uint8)
    img[40, 100] = 255
    up = cv2.resize(img, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    rows, cols = np.nonzero(up)
    ray_point = cam.backproject(torch.full((1, 480, 640), 700.0, dtype=torch.float64))[0, 40, 100]
    centre = cam.scaled(3).project(ray_point.reshape(1, 1, 3))[0, 0]
    assert torch.allclose(centre, torch.tensor([cols.mean(), rows.mean()], dtype=torch.float64), atol=1e-9)
    with pytest.raises(ValueError, match="factor"):
        cam.scaled(0)


def test_camera_rig(gen):
    T = _rigid([0, 1, 0], 0.5, [-200.0, 0.0, 100.0], torch.float32)
    rig = CameraRig([kinect_camera(), kinect_camera(T)])
    assert len(rig) == 2 and rig[1].T_cw is not None and list(rig)[0].name == "kinect"
    points = _random_points(gen, (3, 11), torch.float32)
    out = rig.project(points)
    assert out.shape == (2, 3, 11, 2)
    for c, cam in enumerate(rig):
        torch.testing.assert_close(out[c], cam.project(points))
    back = CameraRig.from_dict(json.loads(json.dumps(rig.to_dict())))
    torch.testing.assert_close(back.project(points), out)
    assert rig.to("cpu", torch.float64).project(points.double()).dtype == torch.float64


# ------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: transform_points(torch.eye(4), torch.zeros(4)), r"points must have shape \(\.\.\., N, 3\), got \(4,\)"),
        (lambda: transform_points(torch.eye(3), torch.zeros(2, 3)), r"T must have shape \(\.\.\., 4, 4\)"),
        (lambda: project_points(torch.zeros(5, 2), _K(torch.float32)), r"points_cam must have shape"),
        (lambda: project_points(torch.zeros(5, 3), torch.eye(4)), r"K must have shape \(\.\.\., 3, 3\), got \(4, 4\)"),
        (lambda: project_points(torch.zeros(2, 5, 3), torch.eye(3).expand(3, 3, 3)), r"do not broadcast"),
        (lambda: unproject_pixels(torch.zeros(5, 2), torch.zeros(4), torch.eye(3)), r"do not broadcast"),
        (lambda: depth_to_points(torch.zeros(4, 4), torch.eye(3)), r"depth must have shape \(B, H, W\), got \(4, 4\)"),
        (
            lambda: kinect_camera().project(torch.zeros(4, 3)),
            r"points_world must have shape \(B, N, 3\), got \(4, 3\)",
        ),
        (lambda: kinect_camera().rays(torch.zeros(1, 4, 3)), r"pixels must have shape \(B, N, 2\)"),
        (lambda: Camera(K=torch.eye(4), T_cw=None, width=4, height=4), r"K must have shape \(3, 3\)"),
        (lambda: Camera(K=torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 1, 1]]), T_cw=None, width=4, height=4), r"K must be"),
        (lambda: Camera(K=torch.eye(3), T_cw=torch.eye(4) * 2, width=4, height=4), r"T_cw must be a rigid"),
        (lambda: Camera(K=torch.eye(3), T_cw=torch.eye(3), width=4, height=4), r"T_cw must have shape \(4, 4\)"),
        (lambda: Camera(K=torch.eye(3), T_cw=None, width=0, height=4), r"width must be a positive int"),
        (lambda: CameraRig([]), r"cameras must contain"),
    ],
)
def test_bad_inputs_raise_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_bad_dtypes_raise_type_error():
    with pytest.raises(TypeError, match="points must have a floating point dtype"):
        transform_points(torch.eye(4), torch.zeros(2, 3, dtype=torch.int64))
    with pytest.raises(TypeError, match="T has dtype torch.float64 but points has dtype torch.float32"):
        transform_points(torch.eye(4, dtype=torch.float64), torch.zeros(2, 3))
    with pytest.raises(TypeError, match="points must be a torch.Tensor"):
        transform_points(torch.eye(4), [[0.0, 0.0, 0.0]])
    with pytest.raises(TypeError, match="cameras\\[1\\] must be a Camera"):
        CameraRig([kinect_camera(), "cam"])


def test_reflection_is_not_rigid():
    T = torch.eye(4)
    T[0, 0] = -1.0
    with pytest.raises(ValueError, match="T_cw must be a rigid"):
        kinect_camera(T)


# ------------------------------------------------------------------ CUDA


def test_camera_to_cuda(gen):
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    cam = kinect_camera(_rigid([1, 0, 0], 0.1, [0.0, 0.0, 10.0], torch.float32))
    cuda_cam = cam.to("cuda")
    assert cuda_cam.K.is_cuda and cuda_cam.T_cw.is_cuda and cuda_cam.centre.is_cuda
    points = _random_points(gen, (2, 10), torch.float32)
    torch.testing.assert_close(cuda_cam.project(points.cuda()).cpu(), cam.project(points), atol=1e-3, rtol=0)
    rays = cuda_cam.rays(cuda_cam.project(points.cuda()))
    assert point_to_ray_residual(points.cuda(), rays).norm(dim=-1).max() < 1e-2
    depth = torch.full((1, 480, 640), 500.0, device="cuda")
    assert cuda_cam.backproject(depth).is_cuda and depth_to_normals(depth, cuda_cam.K).is_cuda
    assert CameraRig([cam]).to("cuda").project(points.cuda()).is_cuda
