"""The hand localiser: which depth pixels are a left hand, a right hand or the arm and
body, and where the 21 standard joints of each hand are.

One small fully-convolutional network (:class:`LocaliserNet`) is applied twice per
frame by :class:`HandLocaliser`:

1. **the frame**: the depth map reduced so its long side is ``frame_size`` px (160):
   per-pixel classes (:data:`~torchhand.salient.localiser_data.CLASSES`), from which
   each hand's pixels and box are found;
2. **each hand's box**, widened by half and resized to ``input_size`` (128 px): the
   classes again at a finer scale, and the joints: per joint and hand a heat map (the
   joint's cell), a sub-cell offset and the joint's depth relative to the crop's
   reference depth.

The network sees depth (mm; 0 = no measurement) as two channels: absolute
(``depth / depth_scale_mm``) and relative to a reference depth of the window
(``(depth - reference) / relative_scale_mm``, clipped; the frame's median depth for
the frame pass, the hand's median for the crop pass), so one network serves both
passes, at any distance. Its outputs are at stride 2 of its input.

A tracker can give **hints**, where it expects a hand (the render of the pose it tracked
in the previous frame): a hint that no hand found already covers gets a crop pass of its
own, which finds hands the frame pass took for the body or missed (docs/localiser.md).

Handedness is read from the classes: a hand's pixels vote left or right with their
class probabilities; the share of the winning side is its confidence. Joints are
lifted to 3D with the sensor depth where it agrees with the predicted depth (the joint
lies ``JOINT_INSIDE_MM`` behind the skin) and with the prediction where it does not
(an occluded joint).

Trained on renders, a share of them composited onto real depth frames (``python -m
train.hand_localiser``, docs/localiser.md); ships as ``models/hand_localiser.pt`` and its
ONNX export, run with ONNX Runtime by default (:meth:`HandLocaliser.load`).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, NamedTuple, Optional, Sequence

import cv2
import numpy as np
import torch

from torchhand.io.assets import model_dirs
from torchhand.salient.localiser_data import HANDS
from torchhand.salient.localiser_net import STRIDE, LocaliserConfig, LocaliserNet

__all__ = ["HandLocaliser", "Localisation", "LocatedHand", "DEFAULT_LOCALISER", "DEFAULT_LOCALISER_ONNX",
           "JOINT_INSIDE_MM", "merge_mirrored"]

#: How far a joint centre lies behind the skin the sensor sees (mm).
JOINT_INSIDE_MM = 8.0
#: The hand classes' sides: class 1 + i is side i.
_SIDES = ("left", "right")
#: A hint's silhouette is widened by this many pixels (the hand's motion between frames),
#: and its pixels farther than ``HINT_DEPTH_MM`` from its median depth are left out.
HINT_DILATION_PX = 15
HINT_DEPTH_MM = 150.0
#: A hint gets a crop pass unless a hand found covers this share of its pixels (within
#: HINT_DILATION_PX); a hand found through a hint is dropped when this share of its pixels
#: belongs to a hand found already (:meth:`HandLocaliser._hint_blobs`,
#: :meth:`HandLocaliser._add_hinted`).
HINT_COVERED = 0.5


def _shipped(name: str) -> Path:
    for d in model_dirs():
        if (d / name).is_file():
            return d / name
    return Path(__file__).resolve().parents[2] / "models" / name


DEFAULT_LOCALISER = _shipped("hand_localiser.pt")
DEFAULT_LOCALISER_ONNX = _shipped("hand_localiser.onnx")


class LocatedHand(NamedTuple):
    """One hand found in a frame.

    Attributes:
        side: ``"left"`` or ``"right"``; ``handedness``: the share of its pixels' class
            probability on that side (0.5 .. 1).
        score: mean hand probability of its pixels in the crop pass (0 .. 1).
        mask: (H, W) bool, its pixels at the frame's resolution.
        box: (r0, r1, c0, c1) the window of the crop pass.
        uv: (21, 2) image positions (px) of the standard joints; z: (21,) their depth
            (mm); confidence: (21,) the heat-map peak of each (0 .. 1).
        hinted: found by the crop pass of a hint (the frame pass had no blob there).
    """

    side: str
    handedness: float
    score: float
    mask: np.ndarray
    box: tuple
    uv: np.ndarray
    z: np.ndarray
    confidence: np.ndarray
    hinted: bool = False

    @property
    def model(self) -> str:
        """The shipped model of this side (``hand_left`` / ``hand_right``)."""
        return HANDS[0] if self.side == "left" else HANDS[1]


class Localisation(NamedTuple):
    """The localiser's reading of a frame: ``labels`` (H, W) uint8 class per pixel
    (:data:`CLASSES`; pixels without depth are background) and the hands found, most
    confident first."""

    labels: np.ndarray
    hands: List[LocatedHand]

    def hand(self, side: str) -> Optional[LocatedHand]:
        """The most confident hand of ``side``, or None."""
        return next((h for h in self.hands if h.side == side), None)


def merge_mirrored(out: tuple, mirrored: tuple) -> tuple:
    """The mean of the network's outputs on a batch and on the same batch mirrored left
    to right (a test-time flip). The mirror's outputs are mirrored back: a mirrored
    right hand is a left hand (the two hand classes swap, as in training), the joints'
    heat maps and depths are of either hand, and the sub-cell offsets across change
    sign (a cell's centre maps onto the mirrored cell's centre)."""
    classes, heat, offset, dz = (np.ascontiguousarray(o[..., ::-1]) for o in mirrored)
    classes = classes[:, [0, 2, 1, 3]]
    offset[:, 0::2] *= -1.0
    return tuple((a + b) * np.float32(0.5) for a, b in zip(out, (classes, heat, offset, dz)))


def _softmax(x: np.ndarray, axis: int = 0) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def _resize_nearest(img: np.ndarray, h: int, w: int) -> np.ndarray:
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST)


class HandLocaliser:
    """Runs :class:`LocaliserNet` on depth frames (module docstring).

    Args:
        network: ``(depth (B, 1, H, W) float32 mm, reference (B,) float32) -> the four
            outputs as numpy arrays`` (torch or ONNX Runtime; :meth:`load`).
        config: the network's :class:`LocaliserConfig`.
        min_hand_px: a hand needs at least this many pixels at the frame's resolution.
        max_hands: at most this many hands are reported.
        flip_test: run every input also mirrored left to right, in the same batch, and
            average the two outputs (:func:`merge_mirrored`): ~10 ms more per frame; off
            by default (better on renders, not on the real frames: docs/localiser.md).
    """

    def __init__(self, network, config: LocaliserConfig, min_hand_px: int = 150, max_hands: int = 2,
                 flip_test: bool = False):
        self.network = network
        self.config = config
        self.min_hand_px = int(min_hand_px)
        self.max_hands = int(max_hands)
        self.flip_test = bool(flip_test)

    def _forward(self, depth: np.ndarray, reference: np.ndarray) -> tuple:
        """The network's four outputs on a batch, averaged with its mirror's with
        ``flip_test``."""
        if not self.flip_test:
            return self.network(depth, reference)
        n = len(depth)
        out = self.network(np.concatenate([depth, depth[..., ::-1]]), np.concatenate([reference, reference]))
        return merge_mirrored(tuple(o[:n] for o in out), tuple(o[n:] for o in out))

    @classmethod
    def load(cls, path=None, onnx: bool = True, threads: int = 2, **kwargs) -> "HandLocaliser":
        """The shipped localiser (or ``path``): ONNX Runtime by default, torch with
        ``onnx=False``. The ``.pt`` file beside an ``.onnx`` gives the config."""
        if onnx:
            import onnxruntime as ort

            onnx_path = Path(path) if path is not None else DEFAULT_LOCALISER_ONNX
            if onnx_path.suffix != ".onnx":
                onnx_path = onnx_path.with_suffix(".onnx")
            for need in (onnx_path, onnx_path.with_suffix(".pt")):
                if not need.is_file():
                    raise FileNotFoundError(f"{need}: no such file (a localiser is an .onnx file with its .pt "
                                            "beside it, as python -m train.hand_localiser writes them)")
            config = LocaliserNet.load(onnx_path.with_suffix(".pt")).config
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = int(threads)
            opts.inter_op_num_threads = 1
            errors = ort.capi.onnxruntime_pybind11_state
            try:
                session = ort.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
            except (errors.InvalidProtobuf, errors.Fail) as err:
                raise ValueError(f"{onnx_path}: not a readable ONNX model ({err})") from None

            def forward(depth, reference):
                return tuple(session.run(None, {"depth": depth, "reference": reference}))

            s = config.input_size  # one crop through it: a model that is not a localiser fails here
            try:
                out = forward(np.full((1, 1, s, s), 600.0, np.float32), np.array([600.0], np.float32))
            except (errors.InvalidArgument, errors.Fail) as err:
                raise ValueError(f"{onnx_path}: not a hand localiser's ONNX model ({err})") from None
            if len(out) != 4 or out[0].shape[1] != 4 or out[1].shape[1] != LocaliserNet.JOINTS:
                raise ValueError(f"{onnx_path}: its outputs {[o.shape for o in out]} are not a hand localiser's "
                                 "(classes (B, 4, h, w), joints (B, 21, h, w), ...)")
            return cls(forward, config, **kwargs)
        net = LocaliserNet.load(path if path is not None else DEFAULT_LOCALISER)
        return cls.from_net(net, **kwargs)

    @classmethod
    def from_net(cls, net: LocaliserNet, **kwargs) -> "HandLocaliser":
        net = net.eval()
        device = next(net.parameters()).device

        def forward(depth, reference):
            with torch.no_grad():
                out = net(torch.from_numpy(depth).to(device), torch.from_numpy(reference).to(device))
            return tuple(o.cpu().numpy() for o in out)

        return cls(forward, net.config, **kwargs)

    def locate(self, depth: np.ndarray, hints: Sequence[np.ndarray] = ()) -> Localisation:
        """Classes and hands of one (H, W) depth frame in mm (0 = no measurement).

        ``hints``: (H, W) depth maps (mm, 0 where none) of where hands are expected, e.g.
        a tracker's render of each hand at its previous pose; a hint that no hand found
        from the frame pass's blobs covers gets a crop pass of its own
        (:meth:`_hint_blobs`, :meth:`_add_hinted`)."""
        depth = np.asarray(depth)
        if depth.ndim != 2:
            raise ValueError(f"depth must be one (H, W) frame in mm, got shape {depth.shape} (colour given as depth?)")
        if depth.dtype == np.uint8:
            raise ValueError("depth is 8-bit: expected millimetres (16-bit PNG or float), e.g. a depth "
                             "visualisation was given instead of the depth")
        d = np.nan_to_num(depth.astype(np.float32), nan=0.0)
        valid = d[d > 0]
        if len(valid) and float(np.median(valid)) < 20.0:
            raise ValueError(f"depth looks like metres (median {float(np.median(valid)):.3g}): expected millimetres")
        labels = np.where(d > 0, self._frame_pass(d), 0).astype(np.uint8)
        hands = self._hands(d, self._components(labels))
        for h in hands:
            labels[h.mask] = 1 + _SIDES.index(h.side)
        blobs, merged = self._hint_blobs(d, hints, hands)
        found = [h._replace(hinted=True) for h in self._hands(d, blobs, within=True)]
        hands = self._add_hinted(hands, found, merged)
        for h in hands:
            if h.hinted:
                labels[h.mask] = 1 + _SIDES.index(h.side)
        hands.sort(key=lambda h: -h.score * h.mask.sum() ** 0.25)
        return Localisation(labels, hands[: self.max_hands])

    def _hands(self, d: np.ndarray, comps: List[tuple], within: bool = False) -> List[LocatedHand]:
        """The hands of blobs ``comps`` (:meth:`_components`): every blob's window in one
        batch through the crop pass; ``within``: each hand's pixels inside its blob only (a
        hint's blob: a hand touching another is cut from it there)."""
        if not comps:
            return []
        windows = [self._window(d, comp, box) for comp, box in comps]
        outs = self._forward(np.stack([w[0] for w in windows])[:, None], np.array([w[1] for w in windows]))
        hands = []
        for i, ((comp, _), (_, ref, side, r0, c0)) in enumerate(zip(comps, windows)):
            hand = self._crop_pass(d, comp, [o[i] for o in outs], ref, side, r0, c0, within)
            if hand is not None:
                hands.append(hand)
        return hands

    def _hint_blobs(self, d: np.ndarray, hints: Sequence[np.ndarray], hands: List[LocatedHand]) -> tuple:
        """(the blobs, as :meth:`_components` gives them, of the hints that no hand of
        ``hands`` covers, or that one hand covers with another hint (two hands found as
        one); the indices in ``hands`` of those hands). A blob is the hint's silhouette widened by
        :data:`HINT_DILATION_PX`, its measured pixels within :data:`HINT_DEPTH_MM` of the
        hint's median depth. A hand covers a hint when :data:`HINT_COVERED` of the
        hint's pixels lie within :data:`HINT_DILATION_PX` of it."""
        H, W = d.shape
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * HINT_DILATION_PX + 1,) * 2)
        found = []
        for k, hint in enumerate(hints):
            hint = np.asarray(hint, np.float32)
            if hint.shape != d.shape:
                raise ValueError(f"hints[{k}] has shape {hint.shape}, the depth {d.shape}")
            seen = hint > 0
            n_seen = int(seen.sum())
            if not n_seen:
                continue
            rows, cols = np.flatnonzero(seen.any(1)), np.flatnonzero(seen.any(0))  # the work: the hint's box
            r0, r1 = max(int(rows[0]) - HINT_DILATION_PX, 0), min(int(rows[-1]) + HINT_DILATION_PX + 1, H)
            c0, c1 = max(int(cols[0]) - HINT_DILATION_PX, 0), min(int(cols[-1]) + HINT_DILATION_PX + 1, W)
            box = seen[r0:r1, c0:c1]
            cover = [j for j, h in enumerate(hands) if (box & (cv2.dilate(h.mask[r0:r1, c0:c1].view(np.uint8), kernel)
                                                               > 0)).sum() >= HINT_COVERED * n_seen]
            z, win = float(np.median(hint[seen])), d[r0:r1, c0:c1]
            comp = np.zeros(d.shape, bool)
            comp[r0:r1, c0:c1] = ((cv2.dilate(box.view(np.uint8), kernel) > 0) & (np.abs(win - z) <= HINT_DEPTH_MM)
                                  & (win > 0))
            found.append((cover, comp))
        covers = [c for cover, _ in found for c in cover]
        merged = {c for c in covers if covers.count(c) >= 2}
        out = []
        for cover, comp in found:
            if (not cover or merged & set(cover)) and comp.sum() >= self.min_hand_px:
                rows, cols = np.flatnonzero(comp.any(1)), np.flatnonzero(comp.any(0))
                out.append((comp, (int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1),
                                   int(cols[-1] - cols[0] + 1))))
        return out, merged

    def _add_hinted(self, hands: List[LocatedHand], found: List[LocatedHand], merged: set) -> List[LocatedHand]:
        """``hands`` with the hands ``found`` through hints. One is left out when
        :data:`HINT_COVERED` of it belongs to a hand found already, unless that hand
        covered two hints (its index in ``merged``): such hands give up the new hand's
        pixels, and are dropped when fewer than ``min_hand_px`` remain."""
        out: List[Optional[LocatedHand]] = list(hands)
        for new in found:
            under = [j for j, h in enumerate(out)
                     if h is not None and (h.mask & new.mask).sum() >= HINT_COVERED * new.mask.sum()]
            if any(j not in merged for j in under):
                continue  # the same hand, found already
            for j in under:
                rest = out[j].mask & ~new.mask
                out[j] = out[j]._replace(mask=rest) if rest.sum() >= self.min_hand_px else None
            out.append(new)
        return [h for h in out if h is not None]

    def _frame_pass(self, d: np.ndarray) -> np.ndarray:
        """(H, W) the most probable class of each pixel, from the reduced frame (its
        probabilities resized bilinearly)."""
        H, W = d.shape
        s = self.config.frame_size / max(H, W)
        h, w = int(round(H * s / 8)) * 8, int(round(W * s / 8)) * 8
        small = _resize_nearest(d, h, w)
        valid = small[small > 0]
        ref = np.float32(np.median(valid) if len(valid) else 1000.0)
        out = self._forward(small[None, None], np.array([ref], np.float32))
        p = [cv2.resize(c, (W, H), interpolation=cv2.INTER_LINEAR) for c in _softmax(out[0][0])]
        # argmax over the four classes, the first on ties, by whole-image comparisons in
        # pairs (numpy's argmax along a short axis is 4x slower at 640x480)
        a, b = np.maximum(p[0], p[1]), np.maximum(p[2], p[3])
        return np.where(b > a, (p[3] > p[2]).view(np.uint8) + np.uint8(2), (p[1] > p[0]).view(np.uint8))

    def _components(self, labels: np.ndarray) -> List[tuple]:
        """Hand blobs of the frame pass (left or right class), largest first: (mask, (top
        row, left column, height, width))."""
        hand = ((labels == 1) | (labels == 2)).astype(np.uint8)
        rows, cols = np.flatnonzero(hand.any(1)), np.flatnonzero(hand.any(0))
        if not len(rows):
            return []
        r0, c0 = int(rows[0]), int(cols[0])  # the components of the hand pixels' box only
        n, comp, stats, _ = cv2.connectedComponentsWithStats(hand[r0:rows[-1] + 1, c0:cols[-1] + 1], connectivity=8)
        order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1
        out = []
        for k in order[: 2 * self.max_hands]:
            if stats[k, cv2.CC_STAT_AREA] >= self.min_hand_px:
                mask = np.zeros(hand.shape, bool)
                mask[r0:rows[-1] + 1, c0:cols[-1] + 1] = comp == k
                out.append((mask, (r0 + int(stats[k, cv2.CC_STAT_TOP]), c0 + int(stats[k, cv2.CC_STAT_LEFT]),
                                   int(stats[k, cv2.CC_STAT_HEIGHT]), int(stats[k, cv2.CC_STAT_WIDTH]))))
        return out

    def _window(self, d: np.ndarray, comp: np.ndarray, box: tuple) -> tuple:
        """The crop pass's input for a blob of the frame pass: (the window resized to the
        input size, its reference depth, its side and top-left pixel in the frame)."""
        H, W = d.shape
        S = self.config.input_size
        top, left, height, width = box
        side = int(max(height - 1, width - 1) * 1.5) + 24
        rc, cc = top + (height - 1) / 2, left + (width - 1) / 2
        r0, c0 = int(round(rc - side / 2)), int(round(cc - side / 2))
        crop = np.zeros((side, side), np.float32)
        sr, sc = slice(max(r0, 0), min(r0 + side, H)), slice(max(c0, 0), min(c0 + side, W))
        crop[sr.start - r0:sr.stop - r0, sc.start - c0:sc.stop - c0] = d[sr, sc]
        x = _resize_nearest(crop, S, S)
        zs = d[comp & (d > 0)]
        ref = np.float32(np.median(zs) if len(zs) else np.median(x[x > 0]) if (x > 0).any() else 600.0)
        return x, ref, side, r0, c0

    def _crop_pass(self, d: np.ndarray, comp: np.ndarray, out: list, ref: np.float32,
                   side: int, r0: int, c0: int, within: bool = False) -> Optional[LocatedHand]:
        """The hand of a blob from the network's outputs ``out`` on its window (its
        pixels connected to the blob; ``within``: inside it)."""
        H, W = d.shape
        sr, sc = slice(max(r0, 0), min(r0 + side, H)), slice(max(c0, 0), min(c0 + side, W))
        classes, heat, offset, dz = out
        p = _softmax(classes)
        p_full = np.stack([cv2.resize(c, (side, side), interpolation=cv2.INTER_LINEAR) for c in p])
        win = p_full[:, sr.start - r0:sr.stop - r0, sc.start - c0:sc.stop - c0]
        vote_l, vote_r = float((win[1] * comp[sr, sc]).sum()), float((win[2] * comp[sr, sc]).sum())
        k = 1 if vote_r >= vote_l else 0
        handedness = max(vote_l, vote_r) / max(vote_l + vote_r, 1e-9)
        hand_p = win[1] + win[2]
        mask = np.zeros((H, W), bool)
        mask[sr, sc] = (hand_p > 0.5) & (d[sr, sc] > 0)
        own = cv2.dilate((p[1 + k] > 0.3).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        uv, z, conf = self._joints(heat, offset, dz, own, ref, side, r0, c0)
        mask &= self._depth_gate(d, z, conf)
        # the blob the hand was found from: keep the part connected to it
        n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
        keep = np.unique(lab[mask & comp])
        mask &= np.isin(lab, keep[keep > 0])
        if within:
            mask &= comp
        if mask.sum() < self.min_hand_px:
            return None
        uv, z = uv.astype(np.float32), self._lift(d, mask, uv, z).astype(np.float32)
        score = float(hand_p[mask[sr, sc]].mean())
        return LocatedHand(_SIDES[k], handedness, score, mask, (r0, r0 + side, c0, c0 + side), uv, z,
                           conf.astype(np.float32))

    def _joints(self, heat, offset, dz, own: np.ndarray, ref: float, side: int, r0: int, c0: int) -> tuple:
        """Joints of the crop pass's maps, each the best cell on the hand's own pixels
        (``own``, the cells of its class, widened; the whole crop when empty), in frame
        pixels."""
        J = LocaliserNet.JOINTS
        hm = np.where(own[None], heat, -np.inf) if own.any() else heat
        h, w = hm.shape[1:]
        flat = hm.reshape(J, -1).argmax(1)
        cy, cx = flat // w, flat % w
        j = np.arange(J)
        du, dv = offset[2 * j, cy, cx], offset[2 * j + 1, cy, cx]
        u_in = (cx + 0.5 + du) * STRIDE - 0.5  # cell centre (in input px) + offset
        v_in = (cy + 0.5 + dv) * STRIDE - 0.5
        s = side / self.config.input_size
        uv = np.stack([c0 + (u_in + 0.5) * s - 0.5, r0 + (v_in + 0.5) * s - 0.5], 1)
        z = ref + dz[j, cy, cx] * self.config.relative_scale_mm
        conf = 1.0 / (1.0 + np.exp(-heat[j, cy, cx]))
        return uv, z, conf

    @staticmethod
    def _depth_gate(d: np.ndarray, z: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """Pixels within the depth span of the confident joints (+-60 mm)."""
        good = z[conf >= 0.2] if (conf >= 0.2).sum() >= 3 else z
        lo, hi = float(np.min(good)) - 60.0, float(np.max(good)) + 60.0
        return (d >= lo) & (d <= hi)

    @staticmethod
    def _lift(d: np.ndarray, mask: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Joint depths: the sensor's (hand pixels within 2 px) + JOINT_INSIDE_MM where it
        agrees with the prediction within 25 mm, else the prediction."""
        H, W = d.shape
        out = z.copy()
        for i, (u, v) in enumerate(uv):
            r, c = int(round(v)), int(round(u))
            if not (0 <= r < H and 0 <= c < W):
                continue
            win = d[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3][mask[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3]]
            if len(win):
                seen = float(np.median(win)) + JOINT_INSIDE_MM
                if abs(seen - z[i]) < 25.0:
                    out[i] = seen
        return out
