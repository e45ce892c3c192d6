"""Camera rigs: several cameras seeing one scene, and where to place them.

:class:`CameraRig` batches the projection of world points into every camera of a rig;
:func:`look_at` and :func:`camera_ring` place cameras around a scene (a studio rig as in
Ballan et al.). The conventions are :mod:`torchhand.geometry.camera`'s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import torch

from torchhand.core.check import check_same, check_tensor
from torchhand.geometry.camera import Camera, _project, _transform, kinect_camera

__all__ = ["CameraRig", "look_at", "camera_ring"]


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """(4, 4) float64 world-to-camera transform of a camera at ``eye`` looking at
    ``target`` (OpenCV: z forward, y down), ``up`` the world direction that appears up
    in the image (camera 0's -y by default)."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    z = torch.as_tensor(target, dtype=torch.float64) - eye
    if float(z.norm()) < 1e-9:
        raise ValueError(f"look_at: eye and target coincide at {eye.tolist()}")
    z = z / z.norm()
    x = torch.linalg.cross(-torch.as_tensor(up, dtype=torch.float64), z)
    if float(x.norm()) < 1e-9:
        raise ValueError(f"look_at: the viewing direction {z.tolist()} is parallel to up {list(up)}")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: the camera axes in world coordinates
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def camera_ring(count: int = 8, distance: float = 650.0, like: Camera | None = None,
                elevations_deg: Sequence[float] = (25.0, -15.0)) -> list:
    """``count`` cameras around the point ``(0, 0, distance)`` of camera 0's axis, all
    at ``distance`` from it and looking at it (a studio rig as in Ballan et al.: the
    scene seen from all sides). Camera 0 is ``like`` (the thesis' Kinect by default) at
    the origin, so world coordinates stay camera 0's; camera k sits at azimuth
    360 k / count degrees about the vertical through the centre, alternately raised and
    lowered by ``elevations_deg``. All share ``like``'s intrinsics and size."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be a positive int (cameras), got {count!r}")
    if not distance > 0:
        raise ValueError(f"distance must be > 0 mm, got {distance}")
    base = kinect_camera(dtype=torch.float64) if like is None else like.to(dtype=torch.float64)
    centre = torch.tensor([0.0, 0.0, float(distance)], dtype=torch.float64)
    cams = []
    for k in range(count):
        if k == 0:
            T = base.T_cw
        else:
            az = 2 * math.pi * k / count
            el = math.radians(elevations_deg[(k - 1) % len(elevations_deg)]) if elevations_deg else 0.0
            # from the centre back towards camera 0 (-z), turned about the vertical (y)
            # by az and raised (towards -y) by el
            d = torch.tensor([-math.sin(az) * math.cos(el), -math.sin(el), -math.cos(az) * math.cos(el)],
                             dtype=torch.float64)
            T = look_at(centre + distance * d, centre)
        cams.append(dataclasses.replace(base, T_cw=T, name=f"{base.name}{k}" if count > 1 else base.name))
    return cams


class CameraRig(Sequence):
    """An ordered, immutable collection of cameras observing the same scene.

    All cameras must share dtype and device so that projections can be batched.
    """

    def __init__(self, cameras: Sequence[Camera]) -> None:
        cameras = tuple(cameras)
        if len(cameras) == 0:
            raise ValueError("cameras must contain at least one Camera, got an empty sequence")
        for i, cam in enumerate(cameras):
            if not isinstance(cam, Camera):
                raise TypeError(f"cameras[{i}] must be a Camera, got {type(cam).__name__}")
        check_same([f"cameras[{i}].K" for i in range(len(cameras))], [c.K for c in cameras])
        self._cameras = cameras

    def __len__(self) -> int:
        return len(self._cameras)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return CameraRig(self._cameras[index])
        return self._cameras[index]

    def __repr__(self) -> str:
        return f"CameraRig({[c.name for c in self._cameras]})"

    @property
    def K(self) -> torch.Tensor:
        """(C, 3, 3) stacked intrinsics."""
        return torch.stack([c.K for c in self._cameras])

    @property
    def T_cw(self) -> torch.Tensor:
        """(C, 4, 4) stacked world-to-camera transforms."""
        return torch.stack([c.T_cw for c in self._cameras])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> CameraRig:
        """Return a copy with every camera moved/cast."""
        return CameraRig([c.to(device, dtype) for c in self._cameras])

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Project world points into every camera.

        Args:
            points: (B, N, 3) world points, mm.

        Returns:
            (C, B, N, 2) pixel coordinates, C = number of cameras.
        """
        check_tensor(points, "points", (None, None, 3), spec="(B, N, 3)", floating=True)
        if points.device != self._cameras[0].device:
            raise ValueError(f"points is on {points.device} but the rig is on {self._cameras[0].device}; use rig.to()")
        K = self.K.to(points.dtype)[:, None]  # (C, 1, 3, 3)
        T = self.T_cw.to(points.dtype)[:, None]  # (C, 1, 4, 4)
        return _project(_transform(T, points[None]), K)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe representation: ``{"cameras": [camera.to_dict(), ...]}``."""
        return {"cameras": [c.to_dict() for c in self._cameras]}

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> CameraRig:
        """Inverse of :meth:`to_dict`."""
        if "cameras" not in data:
            raise ValueError("camera rig dict is missing key 'cameras'")
        return cls([Camera.from_dict(d, dtype=dtype, device=device) for d in data["cameras"]])
