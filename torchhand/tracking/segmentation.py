"""Hand segmentation for real scenes: which depth pixels are the hands.

A real recording holds the body, the arm and maybe a table, not floating hands. Per
frame (:func:`segment_hands`):

1. keep the working range ``[near, far]`` mm and, with ``remove_plane``, drop the
   dominant plane (RANSAC, as :func:`~torchhand.tracking.preprocess.preprocess_depth`);
2. split the valid pixels into depth-connected blobs: neighbours belong together when
   their depths differ by less than ``jump`` mm (a hand in front of the body is cut
   from it by the depth step at its outline);
3. ``mode="auto"`` (the default): the learned hand localiser
   (:mod:`torchhand.salient.localiser`) classifies every pixel as background, left
   hand, right hand or arm and body, and finds each hand's 21 joints and handedness;
   the hands are its most confident hands, those of the scene's sides first (a second
   hand of the same side, or a hand clearly (handedness >= 0.8) of a side the scene has
   no model for, is reported in ``Segmentation.note`` and its pixels are unknown to the tracker); the arm's and
   body's pixels within a hand's window are ``cut`` (unknown, not free space). When it
   finds no hand scoring ``min_score`` or more, the blob rules below decide, and
   ``note`` says so. ``localiser``: the ``.onnx`` file of a localiser of one's own
   (``python -m train.hand_localiser``; "" = the shipped one), ``localiser_flip``: its
   test-time flip (:class:`~torchhand.salient.localiser.HandLocaliser`);
   ``mode="blobs"``: the hands are the ``hands`` nearest blobs (by their 5th percentile
   depth) whose area is that of a hand (``min_area_mm2`` .. ``max_area_mm2``, measured
   in the blob's own depth, so the choice does not depend on the distance); a blob
   within ``depth_band`` mm of its nearest point is kept, the rest of it (the body
   behind a hand that touches it) is dropped. ``mode="range"``: every valid pixel in
   the range is hand, nothing is cut (floating renders, or a user's own ``--near/--far``);
4. (blobs) cut at the wrist: the palm centre is the blob point deepest inside the blob (the
   maximum of its distance transform, in mm); the forearm is the part of the blob
   beyond ``reach_mm`` of the palm centre that reaches farthest (a forearm is longer
   than any finger); the data beyond a plane at ``wrist_cut_mm`` from the palm
   centre along the forearm's direction is dropped. The shipped hands end 69 mm from
   their palm centre (32 mm of forearm beyond the wrist), the default cut. No part
   reaching beyond ``reach_mm`` means no forearm in view: nothing is cut.

``mode="skin"`` (in-hand scanning, thesis Sec. 5.3.1) needs the colour image: the
hands are the skin-coloured pixels in the range (:func:`skin_mask`), their largest
``hands`` connected blobs; the other valid pixels in the range (the held object) are
*unknown* to the tracker (``cut``), not free space.

With two hands the blobs are told apart by the image column of their palm centres
(the right hand on the image's left for a camera facing the person, which is how the
initialisation assigns them: :mod:`torchhand.tracking.initialization`).

Thresholds are in mm of the scene, not pixels, so they hold at any distance; the
defaults suit hands 0.3-1.5 m from a depth camera and are documented in docs/real.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from typing import Dict, List, NamedTuple, Optional, Sequence

import cv2
import numpy as np
import torch

from torchhand.core.errors import UsageError
from torchhand.geometry.camera import Camera

__all__ = ["SegmentConfig", "Segmentation", "SegmentationError", "segment_hands", "locate_hands", "skin_mask",
           "SEGMENT_MODES", "shared_localiser"]

#: the segmentation modes: none (all valid data), range (the depth range only), auto
#: (the learned localiser, the blob rules as fallback), blobs (the blob rules), skin (the
#: skin-coloured pixels of the colour image)
SEGMENT_MODES = ("none", "range", "auto", "blobs", "skin")


class SegmentationError(UsageError):
    """A frame has no hand-sized blob in range, no hand the localiser finds, or more
    blobs than hands asked for: the data's, not a bug (a ``ValueError``)."""


@dataclass(frozen=True)
class SegmentConfig:
    """See the module docstring. ``strict``: two hand-sized blobs in front when one hand
    was asked for is an error (the CLI's default; the tracker takes the nearest)."""

    mode: str = "auto"
    hands: int = 1
    near: float = 200.0
    far: float = 1500.0
    remove_plane: bool = False
    plane_distance: float = 8.0
    jump: float = 20.0
    depth_band: float = 250.0
    min_area_mm2: float = 3000.0
    max_area_mm2: float = 60000.0
    reach_mm: float = 140.0
    wrist_cut_mm: float = 69.0
    strict: bool = False
    min_score: float = 0.5
    localiser: str = ""
    localiser_flip: bool = False

    def __post_init__(self) -> None:
        if self.mode not in SEGMENT_MODES:
            raise ValueError(f"segmentation mode must be one of {SEGMENT_MODES}, got {self.mode!r}")
        if self.hands not in (1, 2):
            raise ValueError(f"hands must be 1 or 2, got {self.hands!r}")
        if not 0 <= self.near < self.far:
            raise ValueError(f"need 0 <= near < far, got near={self.near}, far={self.far}")

    def to_dict(self) -> Dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Dict) -> "SegmentConfig":
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown segmentation settings {unknown}; known: {sorted(known)}")
        return cls(**d)


class Segmentation(NamedTuple):
    """mask: (H, W) bool, the hands' pixels; blobs: one (H, W) bool mask per hand,
    ordered by image column of the palm centre (left to right); palms: (n, 3) camera-
    frame palm centres (mm); forearm: (n, 3) unit directions from the palm centre
    towards the forearm (zeros where none was seen); cut: (H, W) bool, the pixels
    dropped by the wrist cut (or, with the localiser, the arm and body near a hand).

    With the localiser (``mode="auto"``): ``located`` holds each blob's
    :class:`~torchhand.salient.localiser.LocatedHand` (joints, handedness), ``labels`` its
    class of every pixel (:data:`~torchhand.salient.localiser_data.CLASSES`; 255 where
    the sensor measured nothing: the fit check's evidence), ``source`` is
    ``"localiser"`` (``"blobs"`` for the blob rules, also as the fallback) and ``note``
    says what a user should know (a fallback, an extra hand). ``measured``: the depth
    the hands were found in (mm, 0 outside the range and on a removed plane): what
    surrounds them, for the fit check (:func:`~torchhand.scoring.metrics.surrounded`)."""

    mask: np.ndarray
    blobs: List[np.ndarray]
    palms: np.ndarray
    forearm: np.ndarray
    cut: np.ndarray
    located: tuple = ()
    labels: Optional[np.ndarray] = None
    source: str = "blobs"
    note: str = ""
    measured: Optional[np.ndarray] = None

    def apply(self, depth: np.ndarray) -> np.ndarray:
        """The depth the tracker sees: the hands' pixels, 0 elsewhere, and NaN on the
        forearm cut away at the wrist. NaN means *unknown*: the sensor saw something
        there that is not the hand, so a model's wrist reaching over it is no evidence
        against the fit (the free-space term, the fit quality and the initialisation's
        search leave those pixels out), whereas 0 means nothing to explain."""
        out = np.where(self.mask, depth, 0).astype(np.float32)
        out[self.cut & ~self.mask] = np.nan
        return out


def skin_mask(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) bool skin-coloured pixels.

    The explicit YCrCb rule of Chai and Ngan (1999), 133 <= Cr <= 173 and
    77 <= Cb <= 127, a fixed box around skin tones that is independent of brightness;
    the thesis uses the Gaussian mixtures of Jones and Rehg (2002), whose trained
    parameters do not ship with it. Small specks are removed by a 3x3 opening.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"skin segmentation needs an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    ycrcb = cv2.cvtColor(rgb, cv2.COLOR_RGB2YCrCb)
    cr, cb = ycrcb[..., 1], ycrcb[..., 2]
    mask = ((cr >= 133) & (cr <= 173) & (cb >= 77) & (cb <= 127)).astype(np.uint8)
    return cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0


def _skin_blobs(d: np.ndarray, valid: np.ndarray, rgb: Optional[np.ndarray], hands: int, where: str,
                min_pixels: int = 20) -> list:
    if rgb is None:
        raise SegmentationError(f"{where}skin segmentation needs the colour frame, and the sequence has none")
    skin = skin_mask(rgb) & valid
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(skin.astype(np.uint8), connectivity=8)
    if n <= 1:
        raise SegmentationError(f"{where}no skin-coloured pixels with depth in range")
    # the hand's skin falls apart where the held object covers it: every fragment of at
    # least min_pixels goes to the nearest of the ``hands`` largest blobs
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(-areas) + 1
    seeds = order[:hands]
    blobs = [labels == k for k in seeds]
    for k in order[hands:]:
        if stats[k, cv2.CC_STAT_AREA] < min_pixels:
            continue
        d2 = [np.sum((centroids[k] - centroids[j]) ** 2) for j in seeds]
        blobs[int(np.argmin(d2))] |= labels == k
    return blobs


def segment_hands(depth: np.ndarray, camera: Camera, config: SegmentConfig = SegmentConfig(),
                  frame: Optional[str] = None, rgb: Optional[np.ndarray] = None, sides: Sequence[str] = (),
                  localiser=None, hints: Sequence[np.ndarray] = ()) -> Segmentation:
    """Segment the hands of one depth map (H, W) in mm (0 = no measurement).

    ``frame`` names the frame in error messages; ``rgb``: the (H, W, 3) uint8 colour
    frame, needed by ``mode="skin"``; ``sides``: the scene's hands (``"left"`` /
    ``"right"``, one per hand model) that the localiser looks for; ``localiser``: a
    :class:`~torchhand.salient.localiser.HandLocaliser` (default: the shipped one,
    loaded once per process); ``hints``: (H, W) depth maps of where the hands are
    expected (the previous frame's tracked hands, rendered), where the localiser looks
    again (:meth:`~torchhand.salient.localiser.HandLocaliser.locate`). Raises
    :class:`SegmentationError` when no hand is found,
    or (``strict``) when more blobs than hands stand in front.
    """
    where = f"{frame}: " if frame else ""
    d = np.asarray(depth, np.float32)
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"{where}depth has shape {d.shape}, the camera is {camera.height}x{camera.width}")
    if rgb is not None and np.asarray(rgb).shape[:2] != d.shape:
        raise ValueError(f"{where}colour frame has shape {np.asarray(rgb).shape}, the depth {d.shape}")
    valid = np.isfinite(d) & (d >= config.near) & (d <= config.far)
    d = np.where(valid, d, 0).astype(np.float32)
    if config.remove_plane and valid.any():
        from torchhand.tracking.preprocess import remove_plane

        d = remove_plane(d, camera, config.plane_distance)
        valid = d > 0
    H, W = d.shape
    empty = np.zeros((H, W), bool)
    if not valid.any():
        raise SegmentationError(f"{where}no depth between {config.near:g} and {config.far:g} mm")
    fx, fy = camera.fx, camera.fy
    note, labels = "", None
    if config.mode == "auto":
        found = locate_hands(d, camera, config, sides, localiser, where, hints)
        if found.source == "localiser":
            return found._replace(measured=d)
        note = f"the hand localiser found no hand scoring {config.min_score:g} or more; the blob rules decided"
        config, labels = replace(config, mode="blobs"), found.labels
    if config.mode in ("none", "range"):
        blobs = [valid]
    elif config.mode == "skin":
        blobs = _skin_blobs(d, valid, rgb, config.hands, where)
    else:
        blobs = _hand_blobs(d, valid, fx, fy, config, where)
    points = _points(d, camera)
    out, palms, arms, cut = [], [], [], empty.copy()
    for blob in blobs:
        if config.mode == "blobs":
            palm, arm, keep = _wrist_cut(blob, d, points, fx, config)
        else:  # the data as it is: a palm centre for the seeds, nothing cut
            palm, arm, keep = _palm_centre(blob, d, points, fx)[0], np.zeros(3), blob
        cut |= blob & ~keep
        out.append(keep)
        palms.append(palm)
        arms.append(arm)
    if config.mode == "skin":  # the rest of the range is the held object: unknown, not free space
        cut = valid & ~np.any(out, 0)
    order = np.argsort([_column(p, camera) for p in palms], kind="stable")
    out = [out[k] for k in order]
    mask = np.any(out, 0) if out else empty
    return Segmentation(mask, out, np.array([palms[k] for k in order]).reshape(-1, 3),
                        np.array([arms[k] for k in order]).reshape(-1, 3), cut, labels=labels, note=note,
                        measured=d)


def _column(p: np.ndarray, camera: Camera) -> float:
    return float(camera.fx * p[0] / max(p[2], 1e-6) + camera.cx)


@lru_cache(maxsize=4)
def _pixel_grid(h: int, w: int) -> tuple:
    """(v, u) float32 pixel coordinates of an h x w image (read-only, made once)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    v.flags.writeable = u.flags.writeable = False
    return v, u


def _points(d: np.ndarray, camera: Camera) -> np.ndarray:
    v, u = _pixel_grid(*d.shape)
    return np.stack([(u - camera.cx) * d / camera.fx, (v - camera.cy) * d / camera.fy, d], -1)


def _hand_blobs(d: np.ndarray, valid: np.ndarray, fx: float, fy: float, config: SegmentConfig,
                where: str) -> List[np.ndarray]:
    """The ``config.hands`` nearest hand-sized depth-connected blobs."""
    big = np.where(valid, d, 1e6).astype(np.float32)
    step = np.zeros_like(valid)
    # a pixel next to a depth step larger than `jump` separates blobs (4-neighbourhood)
    dv = np.abs(np.diff(big, axis=0)) > config.jump
    dh = np.abs(np.diff(big, axis=1)) > config.jump
    # mark the farther side of each step, so the near blob keeps its outline
    step[1:] |= dv & (big[1:] > big[:-1])
    step[:-1] |= dv & (big[:-1] > big[1:])
    step[:, 1:] |= dh & (big[:, 1:] > big[:, :-1])
    step[:, :-1] |= dh & (big[:, :-1] > big[:, 1:])
    n, labels, stats, _ = cv2.connectedComponentsWithStats((valid & ~step).astype(np.uint8), connectivity=4)
    candidates = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < 20:
            continue
        blob = labels == k
        z0 = float(np.percentile(d[blob], 1))
        blob = _hand_sized(blob & (d <= z0 + config.depth_band), d, fx, fy, config, z0)
        if blob is None:
            continue
        candidates.append((z0, blob))
    if not candidates:
        raise SegmentationError(
            f"{where}no hand-sized blob ({config.min_area_mm2:g}-{config.max_area_mm2:g} mm^2) between "
            f"{config.near:g} and {config.far:g} mm (give --near/--far around the hands, or --segment range)")
    candidates.sort(key=lambda c: c[0])
    if len(candidates) < config.hands:
        raise SegmentationError(f"{where}{config.hands} hands asked for, {len(candidates)} hand-sized blob found")
    if config.strict and config.hands == 1 and len(candidates) > 1 and candidates[1][0] < candidates[0][0] + 100:
        raise SegmentationError(
            f"{where}two hand-sized blobs within 100 mm of each other in depth (at {candidates[0][0]:.0f} and "
            f"{candidates[1][0]:.0f} mm) but one hand was asked for (pass --hands 2, or narrow --near/--far)")
    return [_attach_fragments(blob, z0, labels, stats, d, fx, fy, config) for z0, blob in candidates[: config.hands]]


def _attach_fragments(blob: np.ndarray, z0: float, labels: np.ndarray, stats: np.ndarray, d: np.ndarray,
                      fx: float, fy: float, config: SegmentConfig) -> np.ndarray:
    """Add back the small pieces that the depth steps cut off a hand: a finger in front of
    the palm, a sensor speck at the outline. A piece joins when it touches the blob, is
    smaller than a hand and lies within the blob's depth band."""
    for _ in range(2):
        ring = cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~blob
        touching = np.unique(labels[ring & (labels > 0)])
        grown = blob.copy()
        for k in touching:
            piece = (labels == k) & ~blob
            z = d[piece]
            if (z.size and float(np.sum((z / fx) * (z / fy))) < config.min_area_mm2
                    and np.percentile(z, 50) <= z0 + config.depth_band):
                grown |= piece
        if grown.sum() == blob.sum():
            break
        blob = grown
    return blob


def _area(blob: np.ndarray, d: np.ndarray, fx: float, fy: float) -> float:
    """mm^2 of a blob: each pixel covers (z/fx) x (z/fy)."""
    z = d[blob]
    return float(np.sum((z / fx) * (z / fy)))


def _hand_sized(blob: np.ndarray, d: np.ndarray, fx: float, fy: float, config: SegmentConfig,
                z0: float) -> Optional[np.ndarray]:
    """The blob if hand-sized; if larger (the body, or a hand touching it through the
    arm), its near part: the connected part of the pixels within a band behind the
    nearest point (its nearest part of hand size), the band narrowed until that part is
    no larger than a hand; None if too small."""
    area = _area(blob, d, fx, fy)
    if area < config.min_area_mm2:
        return None
    if area <= config.max_area_mm2:
        return blob
    for band in (0.8, 0.6, 0.5, 0.4, 0.3):
        near = blob & (d <= z0 + band * config.depth_band)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(near.astype(np.uint8), connectivity=4)
        parts = [labels == k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= 20]
        parts = [(float(np.percentile(d[p], 5)), p) for p in parts if _area(p, d, fx, fy) >= config.min_area_mm2]
        if not parts:
            return None
        part = min(parts, key=lambda c: c[0])[1]  # the nearest hand-sized part
        if _area(part, d, fx, fy) <= config.max_area_mm2:
            return part
    return None


def _palm_centre(blob: np.ndarray, d: np.ndarray, points: np.ndarray, fx: float):
    """The blob point deepest inside it (distance transform in mm) and its pixel."""
    dist = cv2.distanceTransform(blob.astype(np.uint8), cv2.DIST_L2, 5) * np.where(blob, d, 0) / fx  # mm
    r, c = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return points[r, c].astype(np.float64), (r, c)


def _wrist_cut(blob: np.ndarray, d: np.ndarray, points: np.ndarray, fx: float, config: SegmentConfig):
    """(palm centre (3,), forearm direction (3,) or zeros, the kept pixels)."""
    palm, (r, c) = _palm_centre(blob, d, points, fx)
    pts = points[blob].astype(np.float64)
    radial = np.linalg.norm(pts - palm, axis=1)
    outer = np.zeros_like(blob)
    outer[blob] = radial > config.reach_mm
    arm = np.zeros(3)
    if outer.any():
        n, labels = cv2.connectedComponents(outer.astype(np.uint8), connectivity=8)
        far = [radial[(labels[blob] == k)].max() for k in range(1, n)]
        k = 1 + int(np.argmax(far))
        # the forearm's direction: its points just beyond the reach
        part = labels[blob] == k
        near_part = part & (radial < config.reach_mm + 60)
        sel = pts[near_part if near_part.any() else part]
        a = sel.mean(0) - palm
        arm = a / max(np.linalg.norm(a), 1e-9)
    keep = blob.copy()
    if arm.any():
        keep[blob] = (pts - palm) @ arm <= config.wrist_cut_mm
        # the cut may leave islands (a finger bent back across the plane stays; far
        # scraps of the forearm go): keep the component holding the palm centre
        n, labels = cv2.connectedComponents(keep.astype(np.uint8), connectivity=8)
        if labels[r, c] > 0:
            keep = labels == labels[r, c]
    return palm, arm, keep


_LOCALISERS: Dict[tuple, object] = {}
#: A hand of the other side than the scene's model is warned about when the localiser's
#: handedness is at least this clear (its votes on real frames are often near 0.5).
CLEAR_HANDEDNESS = 0.8


def shared_localiser(path: str = "", flip_test: bool = False):
    """The shipped :class:`~torchhand.salient.localiser.HandLocaliser` (ONNX Runtime), or
    the one of ``path`` (an ``.onnx`` file of ``python -m train.hand_localiser``, its
    ``.pt`` beside it), loaded once per process with as many threads as torch has then
    (a scale-out worker runs with one: two workers of two threads each on two cores wait
    on each other); ``flip_test``: :class:`HandLocaliser`'s test-time flip."""
    key = (str(path), bool(flip_test))
    if key not in _LOCALISERS:
        from torchhand.salient.localiser import HandLocaliser

        _LOCALISERS[key] = HandLocaliser.load(path or None, threads=torch.get_num_threads(), flip_test=flip_test)
    return _LOCALISERS[key]


def _back_project(uv: np.ndarray, z: np.ndarray, camera: Camera) -> np.ndarray:
    return np.stack([(uv[:, 0] - camera.cx) * z / camera.fx, (uv[:, 1] - camera.cy) * z / camera.fy, z], 1)


def _cut_forearm(mask: np.ndarray, points: np.ndarray, palm: np.ndarray, arm: np.ndarray,
                 config: SegmentConfig) -> np.ndarray:
    """A located hand's pixels without the forearm: where they reach farther than
    ``reach_mm`` from the palm centre towards the wrist joint (no finger reaches that
    far, so a forearm is in the mask), those beyond ``wrist_cut_mm`` are dropped, as
    the blob rules' wrist cut (the shipped hands end there)."""
    along = (points[mask] - palm) @ arm
    if not len(along) or along.max() <= config.reach_mm:
        return mask
    keep = mask.copy()
    keep[mask] = along <= config.wrist_cut_mm
    return keep


def _forearm_direction(blob: np.ndarray, cut: np.ndarray, labels: np.ndarray, d: np.ndarray, points: np.ndarray,
                       palm: np.ndarray, min_pixels: int = 30) -> np.ndarray:
    """(3,) unit direction from the palm centre to the forearm, or zeros without
    evidence: the pixels cut off the hand as forearm, else the arm-and-body pixels next
    to the hand (within 15 px) whose depth continues the hand's (within 80 mm of the
    palm's, so a torso behind the hand is no forearm)."""
    arm = cut & (d > 0)
    if arm.sum() < min_pixels:
        rows, cols = np.flatnonzero(blob.any(1)), np.flatnonzero(blob.any(0))
        H, W = blob.shape  # the blob's box widened by the ring's 15 px: the same ring, a smaller image
        r0, r1 = max(int(rows[0]) - 15, 0), min(int(rows[-1]) + 16, H)
        c0, c1 = max(int(cols[0]) - 15, 0), min(int(cols[-1]) + 16, W)
        ring = np.zeros_like(blob)
        ring[r0:r1, c0:c1] = cv2.dilate(blob[r0:r1, c0:c1].astype(np.uint8), np.ones((31, 31), np.uint8)).astype(bool)
        ring &= ~blob
        arm = ring & (labels == 3) & (d > 0) & (np.abs(d - palm[2]) < 80.0)
    if arm.sum() < min_pixels:
        return np.zeros(3)
    a = points[arm].astype(np.float64).mean(0) - palm
    n = np.linalg.norm(a)
    return a / n if n > 30.0 else np.zeros(3)


def locate_hands(d: np.ndarray, camera: Camera, config: SegmentConfig, sides: Sequence[str] = (),
                 localiser=None, where: str = "", hints: Sequence[np.ndarray] = ()) -> Segmentation:
    """The localiser's segmentation of a range-clipped depth map ``d`` (see the module).

    Raises :class:`SegmentationError` when it finds no hand at all (a frame of body,
    arm or room only: the blob rules would take a part of the body for a hand). When
    its hands all score below ``config.min_score``, returns an empty segmentation of
    ``source="none"`` holding only its ``labels`` (the caller's blob rules decide).
    """
    loc = (localiser or shared_localiser(config.localiser, config.localiser_flip)).locate(d, hints)
    labels = np.where(d > 0, loc.labels, 255).astype(np.uint8)
    if not loc.hands:
        raise SegmentationError(f"{where}the hand localiser found no hand in view (--segment blobs takes the "
                                "nearest hand-sized depth blob instead)")
    good = [h for h in loc.hands if h.score >= config.min_score]
    if not good:
        H, W = d.shape
        return Segmentation(np.zeros((H, W), bool), [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((H, W), bool),
                            labels=labels, source="none")
    want = list(sides)[: config.hands] if sides else []
    picked, notes = [], []
    for side in want:  # the scene's sides first, each its most confident hand
        h = next((h for h in good if h.side == side and not any(h is p for p in picked)), None)
        if h is not None:
            picked.append(h)
    for h in good:  # then any other hand, up to the number asked for
        if len(picked) < config.hands and not any(h is p for p in picked):
            if want and h.handedness >= CLEAR_HANDEDNESS:
                notes.append(f"a {h.side} hand (handedness {h.handedness:.2f}) is taken for the scene's "
                             f"{' and '.join(want)} hand model(s)")
            picked.append(h)
    for h in good:
        if not any(h is p for p in picked):
            notes.append(f"another {h.side} hand (score {h.score:.2f}) was found and left out")
    H, W = d.shape
    cut = np.zeros((H, W), bool)
    for h in loc.hands:
        r0, r1, c0, c1 = h.box
        win = np.zeros((H, W), bool)
        win[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)] = True
        cut |= win & (loc.labels == 3)
        if not any(h is p for p in picked):
            cut |= h.mask
    order = np.argsort([float(np.mean(h.uv[:, 0])) for h in picked], kind="stable")
    picked = [picked[k] for k in order]
    palms, arms, blobs = [], [], []
    points = _points(d, camera)
    for h in picked:
        j = _back_project(h.uv.astype(np.float64), h.z.astype(np.float64), camera)
        arm = j[0] - j[[5, 9, 13, 17]].mean(0)
        blob = _cut_forearm(h.mask, points, j[[0, 5, 9, 13, 17]].mean(0), arm / max(np.linalg.norm(arm), 1e-9),
                            config)
        if not blob.any():
            blob = h.mask
        # the seeds' palm and forearm direction come from the pixels, as the blob rules'
        # do (the joints seed a search of their own, tracking.initialization): a
        # misplaced wrist still decides where the forearm is cut, but no longer which way
        # the blob's seeds point when nothing was cut
        palm, _ = _palm_centre(blob, d, points, camera.fx)
        palms.append(palm)
        arms.append(_forearm_direction(blob, h.mask & ~blob, labels, d, points, palm))
        blobs.append(blob)
    for h, blob in zip(picked, blobs):
        cut |= h.mask & ~blob
    return Segmentation(np.any(blobs, 0), blobs, np.array(palms).reshape(-1, 3), np.array(arms).reshape(-1, 3),
                        cut & ~np.any(blobs, 0), tuple(picked), labels, "localiser",
                        "; ".join(notes))
