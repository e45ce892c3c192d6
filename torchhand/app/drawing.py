"""Overlays for humans: depth in false colour, projected hand skeletons, videos."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Tuple

import cv2
import numpy as np

from torchhand.io.assets import FINGER_NAMES, HAND_KEYPOINT_NAMES

__all__ = ["HAND_SKELETON", "depth_to_color", "draw_skeleton", "write_video", "plot_curves"]

#: Bones of the 21-keypoint hand skeleton as index pairs into HAND_KEYPOINT_NAMES.
HAND_SKELETON: Tuple[Tuple[int, int], ...] = tuple(
    pair
    for f in FINGER_NAMES
    for pair in zip(
        [HAND_KEYPOINT_NAMES.index(n) for n in ("wrist", f"{f}_mcp", f"{f}_pip", f"{f}_dip")],
        [HAND_KEYPOINT_NAMES.index(n) for n in (f"{f}_mcp", f"{f}_pip", f"{f}_dip", f"{f}_tip")],
    )
)
_FINGER_COLORS = [(0, 0, 255), (0, 200, 255), (0, 255, 0), (255, 128, 0), (255, 0, 255)]  # BGR


def depth_to_color(depth: np.ndarray, near: float | None = None, far: float | None = None) -> np.ndarray:
    """(H, W) depth in mm (0 = invalid) -> (H, W, 3) uint8 BGR, turbo colour map, black where invalid."""
    valid = depth > 0
    if not valid.any():
        return np.zeros(depth.shape + (3,), np.uint8)
    near = float(depth[valid].min()) if near is None else near
    far = float(depth[valid].max()) if far is None else far
    scaled = np.clip((depth - near) / max(far - near, 1e-6), 0, 1)
    img = cv2.applyColorMap((255 * (1 - scaled)).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~valid] = 0
    return img


def draw_skeleton(image: np.ndarray, keypoints_px: np.ndarray, thickness: int = 2) -> np.ndarray:
    """Draw one 21-keypoint hand (P=21, 2) in pixels onto a BGR image (in place, also returned)."""
    pts = np.round(keypoints_px).astype(int)
    for k, (a, b) in enumerate(HAND_SKELETON):
        cv2.line(image, tuple(pts[a]), tuple(pts[b]), _FINGER_COLORS[k // 4], thickness, cv2.LINE_AA)
    for p in pts:
        cv2.circle(image, tuple(p), thickness + 1, (255, 255, 255), -1, cv2.LINE_AA)
    return image


def write_video(frames: Iterable[np.ndarray], path, fps: float = 15.0) -> Path:
    """Write BGR frames to an MP4 (mp4v codec)."""
    path = Path(path)
    writer = None
    for img in frames:
        if writer is None:
            h, w = img.shape[:2]
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
            if not writer.isOpened():
                raise RuntimeError(f"OpenCV cannot write {path}")
        writer.write(img)
    if writer is not None:
        writer.release()
    return path


def plot_curves(curves: dict, path, xlabel: str, ylabel: str, size=(640, 480)) -> Path:
    """Line plot of {label: (x (T,), y (T,))} with y in [0, 1], written as PNG (OpenCV only)."""
    w, h = size
    left, right, top, bottom = 60, 20, 20, 50
    img = np.full((h, w, 3), 255, np.uint8)
    xs = np.concatenate([np.asarray(x, float) for x, _ in curves.values()])
    x0, x1 = float(xs.min()), float(xs.max()) if xs.max() > xs.min() else float(xs.min()) + 1

    def to_px(x, y):
        px = left + (np.asarray(x) - x0) / (x1 - x0) * (w - left - right)
        py = h - bottom - np.asarray(y) * (h - top - bottom)
        return np.stack([px, py], -1).round().astype(np.int32)

    for t in np.linspace(0, 1, 6):  # grid and tick labels
        p = to_px([x0, x1], [t, t])
        cv2.line(img, tuple(p[0]), tuple(p[1]), (225, 225, 225), 1)
        cv2.putText(img, f"{t:.1f}", (8, int(p[0][1]) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    for t in np.linspace(x0, x1, 6):
        p = to_px([t], [0])[0]
        cv2.putText(img, f"{t:g}", (int(p[0]) - 8, h - bottom + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), (0, 0, 0), 1)
    palette = [(200, 80, 0), (0, 120, 255), (40, 160, 40), (0, 0, 200), (160, 0, 160), (100, 100, 100)]
    for k, (label, (x, y)) in enumerate(curves.items()):
        col = palette[k % len(palette)]
        cv2.polylines(img, [to_px(x, y)], False, col, 2, cv2.LINE_AA)
        cv2.putText(img, str(label)[:40], (left + 10, top + 18 + 16 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1)
    cv2.putText(img, xlabel, (w // 2 - 60, h - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.putText(img, ylabel, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    path = Path(path)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot write {path}")
    return path
