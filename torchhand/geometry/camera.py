"""Pinhole camera geometry: projection, back-projection and Plücker rays.

Conventions used throughout ``torchhand``:

* units are millimetres;
* the camera frame has x right, y down, z forward (OpenCV);
* pixel centres lie at integer coordinates, ``u = fx * x / z + s * y / z + cx`` and
  ``v = fy * y / z + cy`` with ``u`` the column and ``v`` the row;
* ``T_cw`` maps world points to camera points, ``X_c = R X_w + t``;
* tensors are batch-first; the pure functions broadcast over leading dimensions.

The math lives in pure functions; :class:`Camera` is a thin container around them
(rigs of several cameras: :mod:`torchhand.geometry.camera_rig`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import kornia.filters
import numpy as np
import torch
import torch.nn.functional as F

from torchhand.core.check import check_broadcast, check_same, check_tensor, fmt_shape
from torchhand.geometry.image_ops import max_filter_3x3

__all__ = [
    "PluckerRays",
    "transform_points",
    "project_points",
    "unproject_pixels",
    "depth_to_points",
    "depth_to_normals",
    "depth_to_points_and_normals",
    "pixel_rays",
    "point_to_ray_residual",
    "Camera",
    "kinect_camera",
]


class PluckerRays(NamedTuple):
    """Lines in Plücker coordinates.

    A point ``X`` lies on the line iff ``X x direction - moment = 0``.

    Attributes:
        direction: (..., N, 3) unit direction of each ray.
        moment: (..., N, 3) ``origin x direction`` for any point ``origin`` on the ray.
    """

    direction: torch.Tensor
    moment: torch.Tensor


# --------------------------------------------------------------------------- pure functions


def _transform(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    # R p + t as a batched matmul; T's leading dims broadcast against points'.
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def _project(points_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    normalized = points_cam / points_cam[..., 2:3]
    # Only the first two rows of K matter because K[2] = [0, 0, 1].
    return normalized @ K[..., :2, :].transpose(-1, -2)


def _normalized_coords(pixels: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Invert the upper-triangular K in closed form: (..., N, 2) pixels -> (..., N, 2)."""
    fx, fy = K[..., None, 0, 0], K[..., None, 1, 1]
    skew, cx, cy = K[..., None, 0, 1], K[..., None, 0, 2], K[..., None, 1, 2]
    yn = (pixels[..., 1] - cy) / fy
    xn = (pixels[..., 0] - cx - skew * yn) / fx
    return torch.stack([xn, yn], dim=-1)


def _invert_rigid(T: torch.Tensor) -> torch.Tensor:
    R_t = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a rigid (or any affine) 4x4 transform to points.

    Args:
        T: (..., 4, 4) homogeneous transform.
        points: (..., N, 3) points; leading dims broadcast with ``T``'s.

    Returns:
        (..., N, 3) transformed points ``R p + t``.
    """
    check_tensor(T, "T", ("...", 4, 4), spec="(..., 4, 4)", floating=True)
    check_tensor(points, "points", ("...", None, 3), spec="(..., N, 3)", floating=True)
    check_same(("points", "T"), (points, T))
    check_broadcast(("T", "points"), (T.shape[:-2], points.shape[:-2]))
    return _transform(T, points)


def project_points(points_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Project camera-frame points to pixels (OpenCV convention, no distortion).

    Points with ``z <= 0`` are not culled; ``z == 0`` gives non-finite pixels.

    Args:
        points_cam: (..., N, 3) points in the camera frame, mm.
        K: (..., 3, 3) intrinsics; leading dims broadcast with ``points_cam``'s.

    Returns:
        (..., N, 2) pixel coordinates ``(u, v)``, u right, v down, pixel centres at integers.
    """
    check_tensor(points_cam, "points_cam", ("...", None, 3), spec="(..., N, 3)", floating=True)
    check_tensor(K, "K", ("...", 3, 3), spec="(..., 3, 3)", floating=True)
    check_same(("points_cam", "K"), (points_cam, K))
    check_broadcast(("K", "points_cam"), (K.shape[:-2], points_cam.shape[:-2]))
    return _project(points_cam, K)


def unproject_pixels(pixels: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Lift pixels with known depth to camera-frame points.

    Args:
        pixels: (..., N, 2) pixel coordinates ``(u, v)``.
        depth: (..., N) camera-frame z in mm (not the ray length).
        K: (..., 3, 3) intrinsics; leading dims broadcast with the others.

    Returns:
        (..., N, 3) camera-frame points.
    """
    check_tensor(pixels, "pixels", ("...", None, 2), spec="(..., N, 2)", floating=True)
    check_tensor(depth, "depth", ("...", None), spec="(..., N)", floating=True)
    check_tensor(K, "K", ("...", 3, 3), spec="(..., 3, 3)", floating=True)
    check_same(("pixels", "depth", "K"), (pixels, depth, K))
    check_broadcast(("pixels", "depth"), (pixels.shape[:-1], depth.shape))
    check_broadcast(("K", "pixels"), (K.shape[:-2], pixels.shape[:-2]))
    xy = _normalized_coords(pixels, K) * depth[..., None]
    return torch.cat([xy, depth[..., None].expand_as(xy[..., :1])], dim=-1)


def _check_depth_image(depth: Any, K: Any) -> torch.Tensor:
    """Validate a (B, H, W) depth map and return K expanded to (B, 3, 3)."""
    check_tensor(depth, "depth", (None, None, None), spec="(B, H, W)", floating=True)
    check_tensor(K, "K", ("...", 3, 3), spec="(3, 3) or (B, 3, 3)", floating=True)
    check_same(("depth", "K"), (depth, K))
    if K.ndim == 2:
        K = K.expand(depth.shape[0], 3, 3)
    elif K.ndim != 3 or K.shape[0] not in (1, depth.shape[0]):
        raise ValueError(f"K must have shape (3, 3) or (B, 3, 3) with B={depth.shape[0]}, got {fmt_shape(K.shape)}")
    return K.expand(depth.shape[0], 3, 3)


def _valid_depth(depth: torch.Tensor) -> torch.Tensor:
    # NaN compares False, so NaN pixels count as invalid too.
    return depth > 0


def depth_to_points(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Back-project a depth map to a camera-frame point map.

    Args:
        depth: (B, H, W) camera-frame z in mm; ``<= 0`` (or NaN) marks invalid pixels.
        K: (3, 3) or (B, 3, 3) intrinsics.

    Returns:
        (B, H, W, 3) camera-frame points; zero at invalid pixels.
    """
    K = _check_depth_image(depth, K)
    valid = _valid_depth(depth)
    # by broadcasting the closed-form inverse of K over rows and columns (kornia's
    # depth_to_3d_v2 leaves out the skew K[0, 1] and builds a pixel grid per call)
    H, W = depth.shape[-2:]
    rows = torch.arange(H, device=depth.device, dtype=depth.dtype)
    cols = torch.arange(W, device=depth.device, dtype=depth.dtype)
    fx, fy, skew = K[:, 0, 0, None, None], K[:, 1, 1, None, None], K[:, 0, 1, None, None]
    yn = (rows[None, :, None] - K[:, 1, 2, None, None]) / fy  # (B, H, 1)
    xn = (cols[None, None, :] - K[:, 0, 2, None, None] - skew * yn) / fx  # (B, H, W)
    z = torch.where(valid, depth, depth.new_zeros(()))
    return torch.stack([xn * z, yn * z, z], -1)


def depth_to_normals(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Per-pixel surface normals of a depth map, pointing towards the camera.

    Sobel gradients (kornia's ``spatial_gradient``, as in kornia's ``depth_to_normals``)
    of the point map of :func:`depth_to_points`; because the Sobel stencil is 3x3, a
    pixel gets a normal only if it and its 8 neighbours are valid (mixing in invalid
    zero points would give garbage). Depth discontinuities between valid pixels are
    not masked.

    Args:
        depth: (B, H, W) camera-frame z in mm, ``<= 0`` (or NaN) marks invalid pixels; H, W >= 2.
        K: (3, 3) or (B, 3, 3) intrinsics.

    Returns:
        (B, H, W, 3) unit normals in the camera frame with ``n . p < 0`` (towards the
        camera); zero where undefined.
    """
    return depth_to_points_and_normals(depth, K)[1]


def depth_to_points_and_normals(depth: torch.Tensor, K: torch.Tensor,
                                backend: str = "torch") -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`depth_to_points` and :func:`depth_to_normals` of one depth map, sharing the
    back-projection: (B, H, W, 3) points and (B, H, W, 3) normals, in the depth's
    dtype (use float32 or float64: the gradients are computed in it).

    ``backend``: ``"torch"`` (kornia's Sobel; any device, differentiable) or
    ``"opencv"`` (the same stencil and borders by OpenCV on the host, results moved to
    the depth's device; no gradient; several times faster on a CPU, for preprocessing
    that runs on the host anyway). The two agree to float rounding
    (tests/test_camera.py)."""
    if depth.ndim == 3 and (depth.shape[-2] < 2 or depth.shape[-1] < 2):
        raise ValueError(f"depth must be at least 2x2 to compute normals, got {fmt_shape(depth.shape)}")
    if backend == "opencv":
        return _points_and_normals_opencv(depth, _check_depth_image(depth, K))
    if backend != "torch":
        raise ValueError(f"backend must be 'torch' or 'opencv', got {backend!r}")
    points = depth_to_points(depth, K)
    g = kornia.filters.spatial_gradient(points.permute(0, 3, 1, 2).contiguous())  # (B, 3, 2, H, W)
    (ax, ay, az), (bx, by, bz) = g[:, :, 0].unbind(1), g[:, :, 1].unbind(1)
    # d/du x d/dv points away from the camera; flip it. The cross product on the
    # component planes avoids the strided copies of linalg.cross on (B, H, W, 3).
    normals = F.normalize(torch.stack([az * by - ay * bz, ax * bz - az * bx, ay * bx - ax * by], -1), dim=-1)
    # Erode the validity mask with the Sobel footprint (min filter == -max filter(-x)).
    keep = max_filter_3x3(-_valid_depth(depth).to(depth.dtype)) < -0.5
    return points, torch.where(keep[..., None], normals, normals.new_zeros(()))


def _points_and_normals_opencv(depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``"opencv"`` backend of :func:`depth_to_points_and_normals`: the points of
    :func:`depth_to_points` on the host, then per image OpenCV's Sobel of their planes
    with replicated borders (kornia's stencil; its 1/8 scale cancels in the
    normalisation), the normals kept where the 3x3 neighbourhood is valid (an erosion
    ignoring the outside, as ``max_filter_3x3``)."""
    import cv2

    if depth.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the opencv backend needs float32 or float64 depth, got {depth.dtype} "
                         "(use backend='torch')")
    host = depth.detach().cpu()
    points = depth_to_points(host, K.detach().cpu())
    normals = np.zeros(tuple(points.shape), host.numpy().dtype)
    for b, (d, p) in enumerate(zip(host.numpy(), points.numpy())):
        planes = [np.ascontiguousarray(p[..., c]) for c in range(3)]  # OpenCV and the products run fastest on planes
        a = [cv2.Sobel(c, -1, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE) for c in planes]  # d/du
        g = [cv2.Sobel(c, -1, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE) for c in planes]  # d/dv
        # d/du x d/dv points away from the camera: flipped, as the torch backend
        n = (a[2] * g[1] - a[1] * g[2], a[0] * g[2] - a[2] * g[0], a[1] * g[0] - a[0] * g[1])
        scale = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        keep = cv2.erode((d > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # NaN compares False
        scale = np.where(keep, 1 / np.maximum(scale, 1e-12), 0).astype(d.dtype)
        for c in range(3):
            normals[b, ..., c] = n[c] * scale
    return points.to(depth.device), torch.as_tensor(normals, device=depth.device)


def pixel_rays(pixels: torch.Tensor, K: torch.Tensor, T_cw: torch.Tensor) -> PluckerRays:
    """World-frame Plücker rays through pixels.

    Args:
        pixels: (..., N, 2) pixel coordinates ``(u, v)``.
        K: (..., 3, 3) intrinsics.
        T_cw: (..., 4, 4) rigid world-to-camera transform.

    Returns:
        PluckerRays with ``direction`` (..., N, 3) unit world-frame directions and
        ``moment`` (..., N, 3) = camera_centre x direction.
    """
    check_tensor(pixels, "pixels", ("...", None, 2), spec="(..., N, 2)", floating=True)
    check_tensor(K, "K", ("...", 3, 3), spec="(..., 3, 3)", floating=True)
    check_tensor(T_cw, "T_cw", ("...", 4, 4), spec="(..., 4, 4)", floating=True)
    check_same(("pixels", "K", "T_cw"), (pixels, K, T_cw))
    check_broadcast(("pixels", "K", "T_cw"), (pixels.shape[:-2], K.shape[:-2], T_cw.shape[:-2]))
    xy = _normalized_coords(pixels, K)
    d_cam = F.normalize(torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1), dim=-1)
    R = T_cw[..., :3, :3]
    # Row-vector form of R^T d; centre = -R^T t.
    direction = d_cam @ R
    centre = -(T_cw[..., None, :3, 3] @ R)  # (..., 1, 3)
    moment = torch.linalg.cross(centre.expand_as(direction), direction, dim=-1)
    return PluckerRays(direction, moment)


def point_to_ray_residual(points: torch.Tensor, rays: PluckerRays) -> torch.Tensor:
    """Residual ``X x d - m`` of points w.r.t. Plücker rays (thesis Eq. 4.8).

    Its norm is the point-to-line distance because ``d`` is unit.

    Args:
        points: (..., N, 3) points, same frame as the rays.
        rays: PluckerRays with (..., N, 3) ``direction`` and ``moment``.

    Returns:
        (..., N, 3) residual vectors.
    """
    check_tensor(points, "points", ("...", None, 3), spec="(..., N, 3)", floating=True)
    if not isinstance(rays, tuple) or len(rays) != 2:
        raise TypeError(f"rays must be a PluckerRays(direction, moment), got {type(rays).__name__}")
    check_tensor(rays[0], "rays.direction", ("...", None, 3), spec="(..., N, 3)", floating=True)
    check_tensor(rays[1], "rays.moment", ("...", None, 3), spec="(..., N, 3)", floating=True)
    check_same(("points", "rays.direction", "rays.moment"), (points, rays[0], rays[1]))
    check_broadcast(("points", "rays.direction", "rays.moment"), (points.shape, rays[0].shape, rays[1].shape))
    direction, moment = torch.broadcast_tensors(rays[0], rays[1])
    points, direction = torch.broadcast_tensors(points, direction)
    return torch.linalg.cross(points, direction, dim=-1) - moment


# --------------------------------------------------------------------------- Camera


def _as_matrix(name: str, value: Any, size: int, dtype: torch.dtype | None) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        try:
            value = torch.as_tensor(value, dtype=dtype or torch.get_default_dtype())
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"{name} must be a ({size}, {size}) tensor or nested list of floats") from err
    check_tensor(value, name, (size, size), floating=True)
    return value


def _check_K(K: torch.Tensor, name: str = "K") -> None:
    if not bool(torch.isfinite(K).all()):
        raise ValueError(f"{name} must be finite")
    if K[2].tolist() != [0.0, 0.0, 1.0] or float(K[1, 0]) != 0.0:
        raise ValueError(f"{name} must be upper triangular with last row [0, 0, 1], got {K.tolist()}")
    if float(K[0, 0]) <= 0 or float(K[1, 1]) <= 0:
        raise ValueError(f"{name} must have positive focal lengths, got fx={float(K[0, 0])}, fy={float(K[1, 1])}")


def _check_rigid(T: torch.Tensor, name: str = "T_cw") -> None:
    if not bool(torch.isfinite(T).all()):
        raise ValueError(f"{name} must be finite")
    T64 = T.detach().to("cpu", torch.float64)
    # Loose enough for float32 round-off (also after a cast to float64); catches scale/shear.
    tol = 1e-4 if T.dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-6
    if not torch.allclose(T64[3], T64.new_tensor([0.0, 0.0, 0.0, 1.0]), atol=tol, rtol=0):
        raise ValueError(f"{name} must be a rigid transform with last row [0, 0, 0, 1], got {T64[3].tolist()}")
    R = T64[:3, :3]
    if not torch.allclose(R.T @ R, torch.eye(3, dtype=torch.float64), atol=tol, rtol=0) or float(torch.det(R)) <= 0:
        raise ValueError(f"{name} must be a rigid transform: its 3x3 rotation block is not orthonormal with det +1")


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera (no distortion).

    Attributes:
        K: (3, 3) intrinsics, upper triangular with last row [0, 0, 1].
        T_cw: (4, 4) rigid world-to-camera transform; None means identity.
        width: image width in pixels.
        height: image height in pixels.
        name: free-form identifier.

    Methods taking points cast the camera to the points' dtype; devices must match.
    """

    K: torch.Tensor
    T_cw: torch.Tensor | None
    width: int
    height: int
    name: str = "camera"

    def __post_init__(self) -> None:
        K = _as_matrix("K", self.K, 3, None)
        T = self.T_cw
        T = torch.eye(4, dtype=K.dtype, device=K.device) if T is None else _as_matrix("T_cw", T, 4, K.dtype)
        check_same(("K", "T_cw"), (K, T))
        _check_K(K)
        _check_rigid(T)
        for field in ("width", "height"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ValueError(f"{field} must be a positive int, got {value!r}")
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a str, got {type(self.name).__name__}")
        # Frozen dataclass: bypass __setattr__ to store the normalised tensors.
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_cw", T)

    # ---------------------------------------------------------------- constructors

    @classmethod
    def from_intrinsics(
        cls,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        T_cw: torch.Tensor | None = None,
        name: str = "camera",
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> Camera:
        """Build a camera from focal lengths and principal point (pixels).

        Args:
            fx, fy: focal lengths in pixels.
            cx, cy: principal point in pixels (pixel centres at integers).
            width, height: image size in pixels.
            T_cw: optional (4, 4) world-to-camera transform; identity if None.
            name: camera name.
            dtype, device: of the stored tensors.
        """
        K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)
        if T_cw is not None:
            T_cw = torch.as_tensor(T_cw, dtype=dtype, device=device)
        return cls(K=K, T_cw=T_cw, width=width, height=height, name=name)

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> Camera:
        """Inverse of :meth:`to_dict`."""
        missing = {"K", "T_cw", "width", "height"} - set(data)
        if missing:
            raise ValueError(f"camera dict is missing keys {sorted(missing)}")
        return cls(
            K=torch.tensor(data["K"], dtype=dtype, device=device),
            T_cw=torch.tensor(data["T_cw"], dtype=dtype, device=device),
            width=int(data["width"]),
            height=int(data["height"]),
            name=str(data.get("name", "camera")),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe representation (nested lists of Python floats)."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.detach().cpu().double().tolist(),
            "T_cw": self.T_cw.detach().cpu().double().tolist(),
        }

    # ---------------------------------------------------------------- properties

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return (self.height, self.width)

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    @property
    def T_wc(self) -> torch.Tensor:
        """(4, 4) camera-to-world transform."""
        return _invert_rigid(self.T_cw)

    @property
    def centre(self) -> torch.Tensor:
        """(3,) camera centre in world coordinates, mm."""
        return self.T_wc[:3, 3]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Camera:
        """Return a copy with tensors on ``device`` and/or cast to floating ``dtype``."""
        K = self.K.to(device=device, dtype=dtype)
        return dataclasses.replace(self, K=K, T_cw=self.T_cw.to(device=device, dtype=dtype))

    def scaled(self, factor: float) -> Camera:
        """The same camera with an image ``factor`` times as large in each direction
        (``width`` and ``height`` rounded): focal lengths times ``factor``, and the
        principal point moved so that the image's outer edges stay where they were
        (pixel centres at integers: x' = factor (x + 1/2) - 1/2, as cv2.resize)."""
        if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not factor > 0:
            raise ValueError(f"factor must be a number > 0, got {factor!r}")
        width, height = round(self.width * factor), round(self.height * factor)
        if width < 1 or height < 1:
            raise ValueError(f"factor {factor} leaves a {self.width}x{self.height} camera with no pixels")
        K = self.K.clone()
        K[:2, :2] = K[:2, :2] * factor
        K[:2, 2] = factor * (K[:2, 2] + 0.5) - 0.5
        return dataclasses.replace(self, K=K, width=width, height=height)

    # ---------------------------------------------------------------- geometry

    def _matrices_for(self, name: str, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if x.device != self.device:
            raise ValueError(f"{name} is on {x.device} but camera {self.name!r} is on {self.device}; use camera.to()")
        return self.K.to(x.dtype), self.T_cw.to(x.dtype)

    def to_camera(self, points_world: torch.Tensor) -> torch.Tensor:
        """World points to the camera frame.

        Args:
            points_world: (B, N, 3) world points, mm.

        Returns:
            (B, N, 3) camera-frame points.
        """
        check_tensor(points_world, "points_world", (None, None, 3), spec="(B, N, 3)", floating=True)
        _, T = self._matrices_for("points_world", points_world)
        return _transform(T, points_world)

    def project(self, points_world: torch.Tensor) -> torch.Tensor:
        """Project world points to pixels.

        Args:
            points_world: (B, N, 3) world points, mm.

        Returns:
            (B, N, 2) pixel coordinates ``(u, v)``.
        """
        check_tensor(points_world, "points_world", (None, None, 3), spec="(B, N, 3)", floating=True)
        K, T = self._matrices_for("points_world", points_world)
        return _project(_transform(T, points_world), K)

    def backproject(self, depth: torch.Tensor) -> torch.Tensor:
        """Lift a depth map to world points.

        Args:
            depth: (B, H, W) camera-frame z in mm, ``<= 0`` invalid. H, W are not checked
                against the camera's size.

        Returns:
            (B, H, W, 3) world points; zero at invalid pixels.
        """
        check_tensor(depth, "depth", (None, None, None), spec="(B, H, W)", floating=True)
        K, _ = self._matrices_for("depth", depth)
        points = depth_to_points(depth, K)
        T_wc = self.T_wc.to(depth.dtype)
        world = _transform(T_wc, points.flatten(1, 2)).view_as(points)
        return torch.where(_valid_depth(depth)[..., None], world, world.new_zeros(()))

    def rays(self, pixels: torch.Tensor) -> PluckerRays:
        """World-frame Plücker rays through pixels.

        Args:
            pixels: (B, N, 2) pixel coordinates ``(u, v)``.

        Returns:
            PluckerRays with (B, N, 3) unit ``direction`` and (B, N, 3) ``moment``.
        """
        check_tensor(pixels, "pixels", (None, None, 2), spec="(B, N, 2)", floating=True)
        K, T = self._matrices_for("pixels", pixels)
        return pixel_rays(pixels, K, T)

    def __repr__(self) -> str:
        return (
            f"Camera(name={self.name!r}, {self.width}x{self.height}, fx={self.fx:g}, fy={self.fy:g}, "
            f"cx={self.cx:g}, cy={self.cy:g}, centre={[round(c, 3) for c in self.centre.tolist()]}, "
            f"dtype={self.dtype}, device={self.device})"
        )


def kinect_camera(
    T_cw: torch.Tensor | None = None,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Camera:
    """The thesis' Primesense/Kinect camera: fx = fy = 525, cx = 319.5, cy = 239.5, 640x480.

    Args:
        T_cw: optional (4, 4) world-to-camera transform; identity if None.
        dtype, device: of the stored tensors.
    """
    return Camera.from_intrinsics(
        525.0, 525.0, 319.5, 239.5, 640, 480, T_cw=T_cw, name="kinect", dtype=dtype, device=device
    )
