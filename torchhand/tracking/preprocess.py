"""Preprocessing of depth and colour frames for tracking (thesis Ch. 4.2.2.1-4.2.2.3;
Ballan et al. 2012, Sec. 3).

Per frame: remove what cannot be the hands or objects (depth range, optionally a
fitted support plane or a user mask), smooth with a bilateral filter, back-project
to points with normals, and find the depth discontinuities (Canny on the depth map;
their depth is the 3x3 average of the thesis because single pixels at
discontinuities are unreliable).

Colour frames (:func:`preprocess_colour`, Ballan's features): the grey image, its
Canny edges with their orientations (the direction of the intensity gradient, taken
modulo pi: whether the hand is brighter or darker than what is behind it is not
known, so an image edge has no sign), and the previous frame's grey image of the same
camera, from which the optical-flow term computes its dense flow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import cv2
import numpy as np
import torch

from torchhand.geometry.camera import Camera, depth_to_points_and_normals

__all__ = ["PreprocessConfig", "DepthFrame", "preprocess_depth", "EmptyFrameError", "remove_plane", "ColourConfig",
           "ColourFrame", "ColourView", "preprocess_colour"]


class EmptyFrameError(ValueError):
    """A frame has no valid depth inside the working range."""


@dataclass(frozen=True)
class PreprocessConfig:
    """near, far: working depth range in mm (thesis: thresholding the depth values).
    remove_plane: fit and remove a dominant plane (a table) with RANSAC (open3d).
    bilateral: (diameter px, sigma depth mm, sigma space px) of the smoothing filter;
        None disables it.
    canny: (low, high) thresholds of Canny on the depth map quantised to
        ``canny_mm_per_level`` mm per 8-bit level.
    hole_size: px, holes up to about this size inside the data are sensor dropouts,
        not silhouettes, and produce no depth-discontinuity pixels.
    """

    near: float = 200.0
    far: float = 1500.0
    remove_plane: bool = False
    plane_distance: float = 8.0
    bilateral: Optional[tuple] = (5, 15.0, 3.0)
    canny: tuple = (20, 60)
    canny_mm_per_level: float = 2.0
    hole_size: int = 7


class DepthFrame(NamedTuple):
    """A preprocessed frame (one camera), tensors on the tracker's device.

    depth: (H, W) mm after masking and smoothing (0 = invalid); mask: (H, W) bool;
    points: (H, W, 3) camera-frame points; normals: (H, W, 3) camera-frame normals
    facing the camera; edges: (E, 2) int64 (row, col) of the depth-discontinuity
    pixels on the near side; edge_depth: (E,) mm, the 3x3 average depth at them;
    raw: (H, W) the input depth in mm as given (NaN and out-of-range values set to 0),
    for terms that run their own detectors on it (salient points); covered: (H, W) bool,
    ``mask`` with its holes up to ``hole_size`` closed: where the sensor saw something
    or lost a few pixels (dropouts, the shadows beside occluding fingers), as opposed to
    where it saw nothing (the free-space term's "nothing"), and the pixels given as NaN
    (unknown: a segmentation cut them away, :meth:`~torchhand.tracking.segmentation.
    Segmentation.apply`).
    """

    depth: torch.Tensor
    mask: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    edges: torch.Tensor
    edge_depth: torch.Tensor
    raw: Optional[torch.Tensor] = None
    covered: Optional[torch.Tensor] = None


def preprocess_depth(depth: np.ndarray, camera: Camera, config: PreprocessConfig = PreprocessConfig(),
                     mask: Optional[np.ndarray] = None, device="cpu", dtype=torch.float32) -> DepthFrame:
    """Preprocess one depth map.

    Args:
        depth: (H, W) float depth in mm (0 = nothing seen, NaN = unknown: no data, but
            no evidence of free space either), an array or a tensor on any device.
        camera: its camera (intrinsics used for back-projection).
        mask: optional (H, W) bool, True where the hands/objects may be.
    Raises:
        EmptyFrameError: when no pixel remains.
    """
    if isinstance(depth, torch.Tensor):  # the OpenCV filters below run on the host, once per frame
        depth = depth.detach().cpu().numpy()
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2 or depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth must have shape ({camera.height}, {camera.width}), got {depth.shape}")
    d = _within(depth, config.near, config.far)
    if mask is not None:
        if mask.shape != d.shape:
            raise ValueError(f"mask must have shape {d.shape}, got {mask.shape}")
        d = np.where(mask, d, 0).astype(np.float32)
    if config.remove_plane:
        d = remove_plane(d, camera, config.plane_distance)
    valid_full = d > 0
    if not valid_full.any():
        raise EmptyFrameError(f"no valid depth between {config.near} and {config.far} mm")
    # Every filter below is local (at most max(bilateral, hole_size) px wide) and
    # background is 0, so it runs on the bounding box of the valid pixels plus a
    # margin and gives the same result as on the whole image at a fraction of the
    # cost (the hands fill a few per cent of a 640x480 frame).
    r0, r1, c0, c1 = _crop_box(valid_full, _margin(config))
    d = d[r0:r1, c0:c1]
    valid = valid_full[r0:r1, c0:c1]
    if config.bilateral is not None:
        dia, s_depth, s_space = config.bilateral
        smooth = cv2.bilateralFilter(d, int(dia), float(s_depth), float(s_space))
        d = np.where(valid, smooth, 0).astype(np.float32)

    # Depth discontinuities: Canny on the quantised depth, kept on the near side only.
    q = np.clip(np.where(valid, d, config.far) / config.canny_mm_per_level, 0, 255 * 64)
    q8 = cv2.convertScaleAbs(q - np.median(q[valid]) + 128)
    canny = cv2.Canny(q8, config.canny[0], config.canny[1], L2gradient=True) > 0
    # near side = a valid pixel next to background or to a pixel > 10 mm farther.
    # Small holes (sensor dropouts) are closed first: their borders are not silhouettes.
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (config.hole_size, config.hole_size))
    closed = cv2.morphologyEx(valid.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    far_neighbour = cv2.dilate(np.where(valid, d, 1e9).astype(np.float32), np.ones((3, 3))) > d + 10.0
    touches_background = ~cv2.erode(closed, np.ones((3, 3), np.uint8)).astype(bool)
    edges = canny & valid & (far_neighbour | touches_background)
    # 3x3 average over valid pixels (thesis: depth at discontinuities is unreliable).
    s = cv2.blur(d, (3, 3))
    n = cv2.blur(valid.astype(np.float32), (3, 3))
    avg = np.where(n > 0, s / np.maximum(n, 1e-6), 0)
    rc = np.argwhere(edges)

    # points and normals on the host, as the filters above, then the crop pasted into
    # whole images: on the host for a CPU tracker, on the device for another (only the
    # crop crosses to it)
    dt = torch.as_tensor(d, dtype=dtype)
    K = camera.K.detach().cpu().to(dtype).clone()
    K[0, 2] -= c0  # the crop's intrinsics
    K[1, 2] -= r0
    H, W = valid_full.shape
    p, n = depth_to_points_and_normals(dt[None], K, backend="opencv")
    full = []
    for crop in (dt, p[0], n[0]):
        whole = torch.zeros((H, W) + crop.shape[2:], dtype=dtype, device=device)
        whole[r0:r1, c0:c1] = crop.to(device)
        full.append(whole)
    covered = np.zeros((H, W), bool)
    covered[r0:r1, c0:c1] = closed.astype(bool)
    covered |= np.isnan(depth)
    return DepthFrame(full[0], torch.as_tensor(valid_full, device=device), full[1], full[2],
                      torch.as_tensor(rc + [r0, c0], dtype=torch.int64, device=device).reshape(-1, 2),
                      torch.as_tensor(avg[rc[:, 0], rc[:, 1]], dtype=dtype, device=device),
                      torch.as_tensor(_within(depth, _TINY, _HUGE), device=device),
                      torch.as_tensor(covered, device=device))


#: The smallest and largest finite positive float32: ``_within(d, _TINY, _HUGE)`` keeps
#: the finite positive depths.
_TINY, _HUGE = float(np.nextafter(np.float32(0), np.float32(1))), float(np.finfo(np.float32).max)


def _within(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W) float32 ``depth`` where it lies in [lo, hi], else 0 (NaN and infinities
    too): OpenCV's range test and masked copy, several times faster than numpy's on a
    whole frame."""
    return cv2.bitwise_and(depth, depth, mask=cv2.inRange(depth, float(lo), float(hi)))


def _margin(config: PreprocessConfig) -> int:
    """Pixels around the valid region that the local filters can reach."""
    dia = int(config.bilateral[0]) if config.bilateral is not None else 0
    return max(dia, config.hole_size, 3) + 2


def _crop_box(valid: np.ndarray, margin: int) -> tuple:
    """(r0, r1, c0, c1): the bounding box of ``valid`` widened by ``margin``, clipped."""
    rows, cols = np.nonzero(valid.any(1))[0], np.nonzero(valid.any(0))[0]
    H, W = valid.shape
    return (max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, H),
            max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, W))


def remove_plane(d: np.ndarray, camera: Camera, distance: float) -> np.ndarray:
    """Zero the pixels of the dominant plane (RANSAC, open3d) when it covers > 20 %."""
    import open3d as o3d

    K = camera.K.double().numpy()
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], 1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, inliers = pc.segment_plane(distance, 3, 200)
    if len(inliers) > 0.2 * len(pts):
        out = d.copy()
        out[v[inliers], u[inliers]] = 0
        return out
    return d


@dataclass(frozen=True)
class ColourConfig:
    """blur: sigma in px of the Gaussian smoothing before Canny (0: none); canny: (low,
    high) hysteresis thresholds on the 8-bit grey image's gradient (L2 norm)."""

    blur: float = 1.0
    canny: tuple = (40, 100)

    def __post_init__(self) -> None:
        if not self.blur >= 0 or len(self.canny) != 2 or not 0 <= self.canny[0] <= self.canny[1]:
            raise ValueError(f"need blur >= 0 and 0 <= canny low <= high, got {self}")


class ColourFrame(NamedTuple):
    """A preprocessed colour frame (one camera).

    gray: (H, W) uint8 host array; edges: (E, 2) int64 (row, col) Canny edge pixels;
    edge_phi: (E,) float32 their orientation in [0, pi), the image direction of the
    intensity gradient (the edge's normal) modulo pi; previous: the grey image of the
    same camera's previous frame (None at the first frame); ignore: (H, W) bool host
    array or None, pixels whose features are not used (the occluders of Ballan's
    protocol, for optical flow); salient: (S, 2) float64 (u, v) px salient point
    detections (nails) of the frame, or None; previous_ignore: ``ignore`` of the
    previous frame (the flow between the two is wrong under either's occluders).
    """

    gray: np.ndarray
    edges: torch.Tensor
    edge_phi: torch.Tensor
    previous: Optional[np.ndarray] = None
    ignore: Optional[np.ndarray] = None
    salient: Optional[np.ndarray] = None
    previous_ignore: Optional[np.ndarray] = None


class ColourView(NamedTuple):
    """A colour view as a caller gives it to the tracker: the (H, W, 3) uint8 RGB image,
    optionally the (H, W) bool pixels whose features are ignored and the (S, 2) (u, v)
    px salient point detections."""

    image: np.ndarray
    ignore: Optional[np.ndarray] = None
    salient: Optional[np.ndarray] = None


def preprocess_colour(image, camera: Camera, config: ColourConfig = ColourConfig(), previous: Optional[np.ndarray] = None,
                      ignore: Optional[np.ndarray] = None, device="cpu", dtype=torch.float32,
                      salient: Optional[np.ndarray] = None,
                      previous_ignore: Optional[np.ndarray] = None) -> ColourFrame:
    """Preprocess one colour image: (H, W, 3) uint8 RGB (or (H, W) grey) of ``camera``'s
    size; ``previous``: the grey image of the previous frame (``ColourFrame.gray``);
    ``ignore``: (H, W) bool pixels to leave out of the flow (``previous_ignore``: the
    previous frame's); ``salient``: (S, 2) (u, v) px detections of salient points."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[:2] != (camera.height, camera.width) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"colour image must have shape ({camera.height}, {camera.width}, 3) (or grey "
                         f"({camera.height}, {camera.width})), got {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"colour image must be 8-bit (uint8), got {img.dtype}")
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else np.ascontiguousarray(img)
    for name, other in (("previous", previous), ("ignore", ignore), ("previous_ignore", previous_ignore)):
        if other is not None and np.shape(other) != gray.shape:
            raise ValueError(f"{name} must have shape {gray.shape}, got {np.shape(other)}")
    smooth = cv2.GaussianBlur(gray, (0, 0), config.blur) if config.blur > 0 else gray
    edges = cv2.Canny(smooth, config.canny[0], config.canny[1], L2gradient=True) > 0
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    rc = np.argwhere(edges)
    phi = np.remainder(np.arctan2(gy[rc[:, 0], rc[:, 1]], gx[rc[:, 0], rc[:, 1]]), np.pi)
    if salient is not None:
        salient = np.asarray(salient, np.float64)
        if salient.size and (salient.ndim != 2 or salient.shape[1] != 2 or not np.isfinite(salient).all()):
            raise ValueError(f"salient detections must be finite (S, 2) (u, v) px, got shape {salient.shape}")
        salient = salient.reshape(-1, 2)
    return ColourFrame(gray, torch.as_tensor(rc, dtype=torch.int64, device=device).reshape(-1, 2),
                       torch.as_tensor(phi, dtype=dtype, device=device), previous,
                       None if ignore is None else np.asarray(ignore, bool), salient,
                       None if previous_ignore is None else np.asarray(previous_ignore, bool))
