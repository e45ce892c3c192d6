"""Real sensor frames as training context for the hand localiser: their hands found,
kept as masks, and removed.

A real depth frame of a person holding up a hand shows what the renders only
approximate: a body, an arm, a head with a real sensor's holes, edges and noise. The
localiser's trainer (:mod:`train.hand_localiser`, ``backgrounds``) composites rendered
hands onto such frames; for that the frame's own hand must go, or the network would
learn that a real hand is body. This module

- finds the hand of each frame with the shipped localiser and widens the mask over the
  pixels within 30 mm of the hand's depth span and 15 px of it (fingers the network
  missed, the wrist), and writes the masks to one ``.npz`` (the file's stem -> packed
  bits) with an overlay figure to review them by eye;
- reads a folder's frames with their masks, for the trainer: the frames with the hand
  pixels set to no measurement as backgrounds, the masks as references of its real-frame
  validation.

    python -m train.real_backgrounds --frames ../shared/data/real/sr305/20210326-231615 \\
        --depth-unit-mm 0.125 --out train/data/sr305_231615_hands.npz --figure masks.png

The masks in ``train/data`` were made by this command with the localiser shipped when
they were added; they are data, reviewed on their figure, and are not remade by
training.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from torchhand.data.layout import read_depth

__all__ = ["RealFrames", "hand_mask", "read_real_frames", "main"]


class RealFrames(NamedTuple):
    """depth (N, H, W) float32 mm as recorded; hands (N, H, W) bool, the hand pixels of
    the masks; focal_px of the camera; names (N,) the files' stems."""

    depth: np.ndarray
    hands: np.ndarray
    focal_px: float
    names: tuple

    def without_hands(self) -> np.ndarray:
        """(N, H, W) the depth with the hand pixels set to no measurement (0)."""
        return np.where(self.hands, np.float32(0.0), self.depth)


def _frames(folder: Path) -> list:
    from torchhand.data.importing import depth_files

    return depth_files(folder)


def hand_mask(depth: np.ndarray, localiser) -> np.ndarray:
    """(H, W) bool: the pixels of the most confident hand ``localiser`` finds in
    ``depth`` (mm), widened by 15 px within its depth span +-30 mm and by 3 px."""
    res = localiser.locate(depth)
    if not res.hands:
        return np.zeros(depth.shape, bool)
    m = res.hands[0].mask
    near = cv2.dilate(m.astype(np.uint8), np.ones((31, 31), np.uint8)) > 0
    z = depth[m]
    near &= (depth >= z.min() - 30.0) & (depth <= z.max() + 30.0)
    return cv2.dilate(near.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0


def read_real_frames(folder, depth_unit_mm: float, focal_px: float, masks) -> RealFrames:
    """The depth frames of ``folder`` (16-bit PNGs, ``depth_unit_mm`` per unit) and the
    hand pixels of ``masks`` (a file of :func:`main`)."""
    folder, masks = Path(folder), Path(masks)
    if not masks.is_file():
        raise FileNotFoundError(f"{masks}: no hand masks file (make it with python -m train.real_backgrounds)")
    depth, hands, names = [], [], []
    with np.load(masks) as m:
        for p in _frames(folder):
            if p.stem not in m.files:
                raise ValueError(f"{masks}: no mask for {p} (masks of another folder?)")
            d = read_depth(p, depth_unit_mm)
            if m[p.stem].size != (d.size + 7) // 8:
                raise ValueError(f"{masks}: the mask of {p.name} has {m[p.stem].size * 8} bits, the frame "
                                 f"{d.shape[0]}x{d.shape[1]} pixels (masks of other frames?)")
            h = np.unpackbits(m[p.stem])[: d.size].reshape(d.shape).astype(bool)
            depth.append(d)
            hands.append(h)
            names.append(p.stem)
    return RealFrames(np.stack(depth), np.stack(hands), float(focal_px), tuple(names))


def main(argv=None) -> int:
    class Help(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
        pass

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=Help)
    ap.add_argument("--frames", type=Path, required=True, help="folder of 16-bit depth PNGs")
    ap.add_argument("--depth-unit-mm", type=float, required=True, help="millimetres per depth unit")
    ap.add_argument("--out", type=Path, required=True, help="the masks' .npz (not overwritten)")
    ap.add_argument("--figure", type=Path, help="overlays of the masks (green) to review")
    args = ap.parse_args(argv)
    if args.out.exists():
        raise SystemExit(f"{args.out}: exists; remove it or choose another --out")
    from torchhand.salient.localiser import HandLocaliser

    loc = HandLocaliser.load()
    masks, tiles = {}, []
    for p in _frames(args.frames):
        d = read_depth(p, args.depth_unit_mm)
        m = hand_mask(d, loc)
        masks[p.stem] = np.packbits(m.ravel())
        vis = cv2.cvtColor(np.clip((d - 300.0) / 1200.0 * 255, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        vis[m] = (0.5 * vis[m] + [0, 120, 0]).astype(np.uint8)
        cv2.putText(vis, p.stem, (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
        tiles.append(cv2.resize(vis, (320, 240)))
        print(f"{p.name}: {int(m.sum())} hand pixels")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.stem + ".tmp.npz")
    np.savez_compressed(tmp, **masks)
    tmp.rename(args.out)
    if args.figure is not None:
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 4)
        cv2.imwrite(str(args.figure), np.vstack([np.hstack(tiles[i:i + 4]) for i in range(0, len(tiles), 4)]))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
