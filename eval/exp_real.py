"""The real SR305 frames fitted as a new user would: import, calibrate, track, measure.

For each of the two recordings (8 and 11 frames, 20 captures apart, so not a smooth
sequence): ``torchhand import`` (automatic segmentation), ``torchhand calibrate`` on the
first recording (the same person in both), then ``torchhand track --models my_hand.npz
--write-render --viz --reinit-iou R`` with no init_pose.json (automatic initialisation,
re-initialisation of frames below IoU R). The fit is then measured independently of the
tracker's own log: each frame's written render (``render/NNNNNN.png``) against the
sensor depth segmented by the same segmentation (``--segment``: ``auto``, the hand
localiser, or ``blobs``; hand pixels, arm cut away): the silhouette IoU and the median
|model - data| depth on the overlap; and against the raw sensor depth, which no
segmentation touches: the precision, the share of the model's pixels (where the sensor
measured) whose depth lies within 15 mm of the sensor's.

    python eval/exp_real.py --sr305 ../shared/data/real/sr305 --out out/real/flow --json out/real/sr305.json \
        --figure docs/sr305_fit.png

``--localiser ONNX`` / ``--localiser-flip``: import (and measure) with a localiser of
one's own, or with its test-time flip (as ``torchhand import`` takes them).

The fit check's surround (the share of the hand's surround where the measured surface
goes on at its depth, ``surrounded`` in ``track_log.json``) is read for every tracked
frame, and probed: the frame's fitted silhouette laid on the person's body (the
localiser's arm-and-body pixels, at up to ``--probes`` places per frame where the whole
silhouette lies on them, its depth the measured surface's), as a track of the wrong blob
would lie; ``surround_on_body`` holds those values and ``probes_flagged`` the share
above the fit check's limit.

``--figure``: the 19 frames' overlays (green: the segmented hand, red: the forearm cut
away, the tracked skeleton), each cropped around its hand, in one PNG.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from torchhand.app.cli import main as cli
from torchhand.data.layout import OutputLayout, SequenceLayout, read_depth, read_sequence_info
from torchhand.scoring.metrics import FitCheckLimits, fit_quality, surrounded
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands

INTRINSICS = ["--fx", "476.007", "--fy", "476.007", "--cx", "313.683", "--cy", "242.755", "--depth-unit-mm", "0.125"]


def run(*argv) -> None:
    rc = cli([str(a) for a in argv])
    if rc != 0:
        raise SystemExit(f"torchhand {' '.join(map(str, argv))} failed ({rc})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sr305", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True, help="working folder (replaced)")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--reinit-iou", type=float, default=0.85)
    ap.add_argument("--figure", type=Path, help="write the overlays of all frames, cropped, to this PNG")
    ap.add_argument("--segment", default="auto", choices=("auto", "blobs"), help="the segmentation of import")
    ap.add_argument("--localiser", type=Path, help="an .onnx hand localiser instead of the shipped one")
    ap.add_argument("--localiser-flip", action="store_true", help="the localiser's test-time flip")
    ap.add_argument("--probes", type=int, default=5, help="wrong-blob probes per frame (0: none)")
    args = ap.parse_args()
    recordings = sorted(p for p in args.sr305.iterdir() if p.is_dir())
    if not recordings:
        raise SystemExit(f"{args.sr305}: no recordings")
    if args.out.exists():
        shutil.rmtree(args.out)
    seqs = []
    for rec in recordings:
        run("import", rec, "--out", args.out / rec.name, "--segment", args.segment, *INTRINSICS,
            *(["--localiser", args.localiser] if args.localiser else []),
            *(["--localiser-flip"] if args.localiser_flip else []))
        seqs.append(args.out / rec.name)
    hand = args.out / "my_hand.npz"
    run("calibrate", seqs[0], "--model", "hand_right", "--out", hand)
    run("track", *seqs, "--out", args.out / "track", "--models", hand, "--write-render", "--viz",
        "--reinit-iou", args.reinit_iou)
    rows, tiles, rng = [], [], np.random.default_rng(0)
    for seq in seqs:
        info = read_sequence_info(seq)
        log = json.loads(OutputLayout(args.out / "track" / seq.name).track_log.read_text())["frames"]
        for f in range(info.frames):
            depth = read_depth(SequenceLayout(seq).depth(f), info.depth_unit_mm)
            model = cv2.imread(str(OutputLayout(args.out / "track" / seq.name).render(f)),
                               cv2.IMREAD_UNCHANGED).astype(np.float32)
            try:
                seg = segment_hands(depth, info.cameras[0], SegmentConfig.from_dict(info.segmentation),
                                    sides=("right",))
            except SegmentationError as err:
                rows.append({"recording": seq.name, "frame": f, "error": str(err)})
                continue
            iou, med = fit_quality(model, seg.apply(depth))
            seen = (model > 0) & (depth > 0)
            precision = float((np.abs(model - depth)[seen] < 15.0).mean()) if seen.any() else float("nan")
            tiles.append(_tile(OutputLayout(args.out / "track" / seq.name).overlay(f), seg.mask | (model > 0),
                               f"{seq.name[-6:]}/{f}: IoU {iou:.2f}"))
            rows.append({"recording": seq.name, "frame": f, "iou": iou, "depth_residual_mm": med,
                         "precision": precision, "reinitialized": log[f]["reinitialized"],
                         "tracker_iou": log[f]["iou"], "fit_flagged": log[f].get("fit_flagged"),
                         "surrounded": log[f].get("surrounded"),
                         "surround_on_body": laid_on_the_body(model, seg, float(info.cameras[0].fx), rng,
                                                               args.probes)})
            print(f"{seq.name} frame {f}: IoU {iou:.2f}, precision {precision:.2f}, median depth residual {med:.1f} mm"
                  f"{' (re-initialised)' if log[f]['reinitialized'] else ''}", flush=True)
    ok = [r for r in rows if "iou" in r]
    calib = json.loads(hand.with_suffix(".json").read_text())
    probes = [v for r in ok for v in r["surround_on_body"]]
    summary = {"frames": len(rows), "mean_iou": float(np.mean([r["iou"] for r in ok])),
               "min_iou": float(np.min([r["iou"] for r in ok])),
               "frames_iou_ge_0_8": int(sum(r["iou"] >= 0.8 for r in ok)),
               "min_precision": float(np.min([r["precision"] for r in ok])),
               "frames_precision_ge_0_8": int(sum(r["precision"] >= 0.8 for r in ok)),
               "fit_flagged_frames": int(sum(bool(r["fit_flagged"]) for r in ok)), "segment": args.segment,
               "localiser": str(args.localiser or "shipped") + (" (flip)" if args.localiser_flip else ""),
               "median_depth_residual_mm": float(np.median([r["depth_residual_mm"] for r in ok])),
               "max_frame_depth_residual_mm": float(np.max([r["depth_residual_mm"] for r in ok])),
               "reinitialized_frames": int(sum(r["reinitialized"] for r in ok)),
               "calibration": {"scale": calib["scale"], "fingers": calib["fingers"],
                               "mean_iou_before": calib["mean_iou_before"],
                               "mean_iou_after": calib["mean_iou_after"]},
               "reinit_iou": args.reinit_iou, "surround_limit": FitCheckLimits().surrounded,
               "surround_max": float(np.nanmax([np.nan if r["surrounded"] is None else r["surrounded"] for r in ok])),
               "probes": len(probes), "probes_flagged": float(np.mean(np.array(probes) > FitCheckLimits().surrounded))
               if probes else float("nan"), "per_frame": rows}
    if args.figure is not None:
        cols = 5
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
        grid = np.concatenate([np.concatenate(tiles[r : r + cols], 1) for r in range(0, len(tiles), cols)], 0)
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.figure), grid)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(summary, indent=2))
    print(f"mean IoU {summary['mean_iou']:.2f} (min {summary['min_iou']:.2f}, {summary['frames_iou_ge_0_8']} of "
          f"{len(ok)} frames >= 0.8), precision min {summary['min_precision']:.2f} "
          f"({summary['frames_precision_ge_0_8']} frames >= 0.8), median depth residual {summary['median_depth_residual_mm']:.1f} mm (worst "
          f"frame {summary['max_frame_depth_residual_mm']:.1f} mm); surround of the fits max "
          f"{summary['surround_max']:.2f}, of {summary['probes']} silhouettes laid on the body "
          f"{summary['probes_flagged']:.2f} flagged (limit {summary['surround_limit']:g}) -> {args.json}")


def laid_on_the_body(model: np.ndarray, seg, focal: float, rng, probes: int, tries: int = 200) -> list:
    """The surround of the fitted silhouette (``model``, mm) moved onto the localiser's
    arm-and-body pixels (class 3) at up to ``probes`` random places where all of it lies
    on them, its depth the measured surface there (within its 5-95th percentiles): a
    model tracking the wrong blob. The depth is the segmentation's ``measured``, as the
    tracker's fit check reads it. Empty without the localiser's classes."""
    own = model > 0
    if seg.labels is None or seg.measured is None or not own.any() or probes <= 0:
        return []
    depth = seg.measured
    body = (seg.labels == 3) & (depth > 0)
    rows, cols = np.nonzero(own)
    r0, c0 = int(rows.mean()), int(cols.mean())
    places = np.argwhere(body)
    H, W = own.shape
    out = []
    for _ in range(tries):
        if len(out) == probes or not len(places):
            break
        r, c = places[rng.integers(len(places))]
        rr, cc = rows + r - r0, cols + c - c0
        if rr.min() < 0 or cc.min() < 0 or rr.max() >= H or cc.max() >= W or not body[rr, cc].all():
            continue
        laid = np.zeros_like(own)
        laid[rr, cc] = True
        lo, hi = np.percentile(depth[laid], [5, 95])
        out.append(surrounded(laid, np.where(laid, np.clip(depth, lo, hi), 0), laid, depth, focal))
    return out


def _tile(path: Path, mask: np.ndarray, label: str, size: int = 220) -> np.ndarray:
    """The overlay at ``path`` cropped to a square around ``mask``, ``size`` px, labelled."""
    img = cv2.imread(str(path))
    rows, cols = np.nonzero(mask)
    c, r = (cols.min() + cols.max()) // 2, (rows.min() + rows.max()) // 2
    half = int(max(rows.max() - rows.min(), cols.max() - cols.min()) * 0.6) + 10
    pad = cv2.copyMakeBorder(img, half, half, half, half, cv2.BORDER_CONSTANT)
    tile = cv2.resize(pad[r : r + 2 * half, c : c + 2 * half], (size, size))
    cv2.putText(tile, label, (4, size - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


if __name__ == "__main__":
    main()
