"""The real SR305 frames: segmentation, automatic initialisation and its fit, per frame.

Each of the 19 frames (20 captures apart, so not a smooth sequence) is segmented and
initialised on its own with the shipped right hand (not the recorded person's: no
calibration yet), and the fit is measured without ground truth: the silhouette IoU of
the rendered hand and the segmented data, and the median |model - data| depth on their
overlap (torchhand.scoring.metrics.fit_quality). Writes the JSON and one overlay per
frame (data outline green, model outline red, skeleton) beside it.

    python eval/exp_real.py --sr305 ../shared/data/real/sr305 --json out/real/sr305_init.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from torchhand.app.drawing import depth_to_color, draw_mask_outline, draw_skeleton
from torchhand.data.importing import natural_key
from torchhand.geometry.camera import Camera
from torchhand.model.scene import Scene
from torchhand.scoring.metrics import fit_quality
from torchhand.tracking.initialization import InitConfig, Initializer
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import Tracker, TrackerConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sr305", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--particles", type=int, default=64)
    ap.add_argument("--generations", type=int, default=40)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cam = Camera.from_intrinsics(476.007, 476.007, 313.683, 242.755, 640, 480)
    scene = Scene.from_names(["hand_right"])
    tracker = Tracker(scene, TrackerConfig())
    init = Initializer(tracker, InitConfig(args.particles, args.generations))
    files = sorted(args.sr305.glob("*/*.png"), key=lambda p: (p.parent.name, natural_key(p.name)))
    if not files:
        raise SystemExit(f"{args.sr305}: no frames")
    shots = args.json.parent / (args.json.stem + "_overlays")
    shots.mkdir(parents=True, exist_ok=True)
    rows = []
    for p in files:
        depth = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) / 8.0
        name = f"{p.parent.name}/{p.name}"
        try:
            seg = segment_hands(depth, cam, SegmentConfig())
        except SegmentationError as err:
            rows.append({"frame": name, "error": str(err)})
            continue
        res = init(depth, cam, seg)
        with torch.no_grad():
            posed = scene(res.theta[None])
            model = tracker.renderer(posed.vertices, cam, normals=False).depth[0].numpy()
        data = seg.apply(depth)
        iou, med = fit_quality(model, data)
        rows.append({"frame": name, "iou": iou, "depth_residual_mm": med, "seconds": res.seconds,
                     "search_cost": res.search_cost, "cost": res.cost})
        img = depth_to_color(depth, 400, 1000)
        draw_mask_outline(img, seg.mask, (0, 220, 0))
        draw_mask_outline(img, model > 0, (0, 0, 255))
        draw_skeleton(img, cam.project(posed.keypoints)[0].numpy())
        cv2.imwrite(str(shots / f"{p.parent.name}_{p.stem}.png"), img)
        print(f"{name}: IoU {iou:.2f}, median depth residual {med:.1f} mm, {res.seconds:.1f} s", flush=True)
    ok = [r for r in rows if "iou" in r]
    summary = {"frames": len(rows), "mean_iou": float(np.mean([r["iou"] for r in ok])),
               "min_iou": float(np.min([r["iou"] for r in ok])),
               "median_depth_residual_mm": float(np.median([r["depth_residual_mm"] for r in ok])),
               "mean_seconds": float(np.mean([r["seconds"] for r in ok])), "per_frame": rows}
    args.json.write_text(json.dumps(summary, indent=2))
    print(f"mean IoU {summary['mean_iou']:.2f} (min {summary['min_iou']:.2f}), median depth residual "
          f"{summary['median_depth_residual_mm']:.1f} mm, {summary['mean_seconds']:.1f} s per frame -> {args.json}")


if __name__ == "__main__":
    main()
