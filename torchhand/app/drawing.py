"""Pictures for people: depth in false colour with its colour bar, projected hand
skeletons and object outlines, labels, videos and curves (OpenCV only)."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Tuple

import cv2
import numpy as np

from torchhand.io.assets import FINGER_NAMES, HAND_KEYPOINT_NAMES

__all__ = ["HAND_SKELETON", "GT_COLOR", "OBJECT_COLOR", "depth_range", "depth_to_color", "draw_skeleton", "draw_chain",
           "draw_hull", "draw_mask_outline", "draw_colorbar", "draw_legend", "write_video", "plot_curves",
           "part_colors", "draw_rig", "draw_models", "mosaic"]

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
#: ground-truth skeletons (BGR white)
GT_COLOR = (255, 255, 255)
#: tracked objects (BGR cyan)
OBJECT_COLOR = (255, 255, 0)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def depth_range(depths, low: float = 1.0, high: float = 99.0) -> tuple:
    """(near, far) mm for a whole sequence: the ``low`` and ``high`` percentiles of the
    valid depth of all its (H, W) maps, so that one colour means one depth in every
    frame; (0, 1) when no pixel is valid."""
    valid = np.concatenate([np.asarray(d)[np.asarray(d) > 0].ravel() for d in depths]) if len(depths) else np.zeros(0)
    if valid.size == 0:
        return 0.0, 1.0
    near, far = np.percentile(valid, [low, high])
    return float(near), float(max(far, near + 1.0))


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


def _points(px: np.ndarray) -> np.ndarray:
    px = np.asarray(px, np.float64)
    ok = np.isfinite(px).all(-1) & (np.abs(px) < 1e5).all(-1)  # points behind the camera project anywhere
    return np.round(np.where(ok[:, None], px, 0)).astype(int), ok


def draw_skeleton(image: np.ndarray, keypoints_px: np.ndarray, thickness: int = 2,
                  color: tuple | None = None) -> np.ndarray:
    """Draw one 21-keypoint hand (P=21, 2) in pixels onto a BGR image (in place, also
    returned): bones and joints in one colour per finger, or ``color`` for all."""
    pts, ok = _points(keypoints_px)
    for k, (a, b) in enumerate(HAND_SKELETON):
        c = color or _FINGER_COLORS[k // 4]
        if ok[a] and ok[b]:
            cv2.line(image, tuple(pts[a]), tuple(pts[b]), c, thickness, cv2.LINE_AA)
        if ok[b]:  # the joint at the bone's far end (the wrist below)
            cv2.circle(image, tuple(pts[b]), thickness + 1, c, -1, cv2.LINE_AA)
    if len(pts) and ok[0]:
        cv2.circle(image, tuple(pts[0]), thickness + 2, color or (60, 60, 60), -1, cv2.LINE_AA)
    return image


def draw_chain(image: np.ndarray, points_px: np.ndarray, color: tuple = OBJECT_COLOR) -> np.ndarray:
    """The bone origins (J, 2) of an articulated object as a polyline with dots."""
    pts, ok = _points(points_px)
    for a, b in zip(range(len(pts) - 1), range(1, len(pts))):
        if ok[a] and ok[b]:
            cv2.line(image, tuple(pts[a]), tuple(pts[b]), color, 2, cv2.LINE_AA)
    for p, good in zip(pts, ok):
        if good:
            cv2.circle(image, tuple(p), 3, color, -1, cv2.LINE_AA)
    return image


def draw_hull(image: np.ndarray, points_px: np.ndarray, color: tuple = OBJECT_COLOR) -> np.ndarray:
    """The outline (convex hull) of projected vertices (N, 2) of a rigid object."""
    pts, ok = _points(points_px)
    if ok.sum() >= 3:
        cv2.polylines(image, [cv2.convexHull(pts[ok].astype(np.int32))], True, color, 2, cv2.LINE_AA)
    return image


def draw_mask_outline(image: np.ndarray, mask: np.ndarray, color: tuple, thickness: int = 1) -> np.ndarray:
    """Draw the outline of a (H, W) bool mask (a segmentation) onto a BGR image in place."""
    contours, _ = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(image, contours, -1, color, thickness, cv2.LINE_AA)
    return image


def draw_colorbar(image: np.ndarray, near: float, far: float, width: int = 14) -> np.ndarray:
    """A vertical colour bar of :func:`depth_to_color`'s map at the right edge, labelled
    with ``near`` (top) and ``far`` (bottom) in mm."""
    h, w = image.shape[:2]
    top, bottom = 24, h - 24
    x0 = w - width - 48
    ramp = np.linspace(255, 0, max(bottom - top, 2)).astype(np.uint8)[:, None].repeat(width, 1)
    image[top:bottom, x0 : x0 + width] = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)
    cv2.rectangle(image, (x0, top), (x0 + width, bottom), (255, 255, 255), 1)
    for y, v in ((top, near), (bottom, far)):
        cv2.putText(image, f"{v:.0f}", (x0 + width + 3, y + 4), _FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(image, "mm", (x0 + width + 3, (top + bottom) // 2), _FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def draw_legend(image: np.ndarray, title: str, entries) -> np.ndarray:
    """A title (e.g. the frame number) and ``(label, BGR colour or None)`` entries at the
    top left, on a dark box so they read over any depth colour."""
    lines = [(title, (255, 255, 255))] + [(label, color or (200, 200, 200)) for label, color in entries]
    box_w = 12 + max(cv2.getTextSize(s, _FONT, 0.5, 1)[0][0] for s, _ in lines)
    cv2.rectangle(image, (4, 4), (4 + box_w, 10 + 18 * len(lines)), (40, 40, 40), -1)
    for k, (text, color) in enumerate(lines):
        cv2.putText(image, text, (10, 20 + 18 * k), _FONT, 0.5, color, 1, cv2.LINE_AA)
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


def part_colors(count: int) -> np.ndarray:
    """(count, 3) uint8 RGB, distinct hues for the parts of a segmented mesh."""
    hue = (np.arange(count) * 0.618034 % 1.0 * 179).astype(np.uint8)
    hsv = np.stack([hue, np.full(count, 200, np.uint8), np.full(count, 230, np.uint8)], 1)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


def draw_rig(vertices: np.ndarray, parts: np.ndarray, nodes: np.ndarray, edges: np.ndarray, joints: np.ndarray,
             ends: np.ndarray, branches: np.ndarray, size=(900, 600)) -> np.ndarray:
    """A BGR picture of a rig: the mesh's vertices coloured by part, seen along its
    least extended axis, the curve skeleton (white), the joints with DoF (red), the
    auxiliary joints at the skeleton's ends (cyan) and branches (yellow)."""
    W, H = size
    c = vertices.mean(0)
    axes = np.linalg.svd(vertices - c, full_matrices=False)[2][:2]  # the two main directions

    def to_px(p):
        q = (np.asarray(p).reshape(-1, 3) - c) @ axes.T
        return q

    q = to_px(vertices)
    scale = 0.9 * min(W / max(np.ptp(q[:, 0]), 1e-6), H / max(np.ptp(q[:, 1]), 1e-6))
    mid = (q.max(0) + q.min(0)) / 2

    def px(p):
        r = (to_px(p) - mid) * scale + [W / 2, H / 2]
        return np.round(r).astype(np.int32)

    img = np.full((H, W, 3), 32, np.uint8)
    colors = part_colors(int(parts.max()) + 1)[:, ::-1]
    for (x, y), k in zip(px(vertices), parts):
        if 0 <= x < W and 0 <= y < H:
            img[y, x] = colors[k]
    n = px(nodes) if len(nodes) else np.zeros((0, 2), np.int32)
    for a, b in edges:
        cv2.line(img, tuple(int(v) for v in n[a]), tuple(int(v) for v in n[b]), (255, 255, 255), 1, cv2.LINE_AA)
    for pts, color in ((ends, (255, 255, 0)), (branches, (0, 255, 255)), (joints, (0, 0, 255))):
        for p in px(pts) if len(pts) else []:
            cv2.circle(img, (int(p[0]), int(p[1])), 5, color, -1, cv2.LINE_AA)
    return draw_legend(img, "rig", [("joint (DoF)", (0, 0, 255)), ("skeleton end", (255, 255, 0)),
                                    ("branch", (0, 255, 255))])


def draw_models(image: np.ndarray, scene, posed, f: int, camera, gt_px=None) -> np.ndarray:
    """Frame ``f`` of a posed scene drawn into ``image`` as ``camera`` sees it: hand
    skeletons, the joints of articulated objects, the outlines of rigid ones; with
    ``gt_px`` ((P, 2) px, the scene's keypoints), the ground-truth skeletons in white,
    thin, over the tracked ones, so that both show."""
    for k, (model, out) in enumerate(zip(scene.models, posed.models)):
        if model.kind == "hand":
            draw_skeleton(image, camera.project(out.keypoints[f : f + 1])[0].cpu().numpy())
            if gt_px is not None:
                draw_skeleton(image, gt_px[scene.keypoint_slices[scene.names[k]]], color=GT_COLOR, thickness=1)
        elif model.num_bones > 1:
            draw_chain(image, camera.project(model.joints_from(out.G[f : f + 1]))[0].cpu().numpy())
        else:
            draw_hull(image, camera.project(out.vertices[f : f + 1, ::16])[0].cpu().numpy())
    return image


def mosaic(images, columns: int = 4, scale: float = 0.5) -> np.ndarray:
    """Equal-sized BGR images side by side, ``columns`` to a row, each scaled by ``scale``
    (the views of a camera rig in one picture)."""
    small = [cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) for im in images]
    h, w = small[0].shape[:2]
    rows = -(-len(small) // columns)
    out = np.zeros((rows * h, min(columns, len(small)) * w, 3), np.uint8)
    for k, im in enumerate(small):
        r, c = divmod(k, columns)
        out[r * h : (r + 1) * h, c * w : (c + 1) * w] = im
    return out
