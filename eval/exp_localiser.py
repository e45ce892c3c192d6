"""The hand localiser measured: a realistic synthetic test set, the initialisation it
seeds, its speed, and the real SR305 frames.

    python eval/exp_localiser.py --json docs/localiser.json --figure docs/localiser_sr305.png \
        [--frames 200] [--init-frames 30] [--sr305 ../shared/data/real/sr305]

1. **Test set**: ``--frames`` renders of hands in context
   (:func:`torchhand.salient.localiser_data.render_context_frames`) with a seed never
   used in training (9001), the finger poses of the thesis motions held out of training
   (sequences 03, 10, 20) besides random and curled ones, and the independent
   active-stereo noise model (training used the Kinect one). Measured: the hand-pixel
   IoU per frame (left and right hand pixels together, pixels with depth) for the
   localiser and for the blob rules (``--segment blobs``, nearest hand-sized blob cut at
   the wrist; frames with one hand), the median 2D joint error (px at 640x480) and the
   3D error of the lifted joints (mm) of the hands found, handedness accuracy and the
   share of hands found (joints within 60 px on average), of all rendered hands and of
   those in view (``IN_VIEW_PX`` measured pixels or more: a hand hidden behind an object
   or outside the image cannot be found), and the correlation of the joints' confidence
   with their 2D error. ``hands_found_in_view_with_hint`` and ``hand_iou_mean_with_hint``:
   the same when the localiser is also given, for each hand in view, its true depth
   pixels moved by up to ``HINT_MOTION_PX`` in a random direction as a hint (what
   ``torchhand track`` gives it from the previous frame's fit: the tracked hand's
   render; here simulated).
2. **Initialisation**: ``--init-frames`` one-hand frames (right hand, shipped size) are
   segmented and initialised as ``torchhand track`` does without ``init_pose.json``;
   success = mean error of the 21 joints <= 10 mm; the time per hand.
   ``auto_true_joints``: the same frames and segmentation with the true joints in place
   of the localiser's (what the search does given perfect joints). With
   ``--compare-blobs``, the same frames with the blob rules' seeds.
3. **Speed**: the network at its input size (128 px crop, 160x120 frame) and the whole
   ``locate`` of a 640x480 frame, with and without the test-time flip
   (``HandLocaliser.flip_test``; ``--flip-test`` runs every section with it),
   ONNX Runtime on 2 threads.
4. **SR305** (``--sr305``): the 19 real frames through ``segment_hands`` (auto); the
   figure shows each frame's classes (green hand, blue arm/body) and joints. The fit
   of those frames is measured by ``eval/exp_real.py``.
5. **Seen against unseen** (``--seen CACHE/train.npz``): section 1's measures on the
   first ``--seen-frames`` frames the network was trained on and on as many new renders
   of the training noise family (Kinect; seed 777, the held-out motions): equal figures
   mean the network underfits (more capacity or steps help), far better seen figures
   that it overfits (more renders help).
6. **The surround** (the fit check's measure from the sensor alone,
   :func:`torchhand.scoring.metrics.surrounded`) on section 1's frames: of every hand in
   view, its true silhouette with the measured depth as its depth (a perfect fit, in
   context: tables, held objects, arms and bodies behind and beside it), and that
   silhouette laid on the frame's arm-and-body pixels at up to ``SURROUND_PROBES`` places
   (a track of the wrong blob, as ``eval/exp_real.py`` probes the real frames):
   ``true_hands_flagged`` is the share of good fits the check would flag,
   ``probes_flagged`` the share of wrong-blob fits it flags.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchhand.salient.localiser import HandLocaliser
from torchhand.salient.localiser_data import IGNORE, ContextConfig, render_context_frames

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # train.hand_localiser's motions, run from any folder
HIA = REPO.parent / "shared" / "data" / "hands_in_action"
TEST_SEED = 9001
HELD_OUT = ["03", "10", "20"]
#: Seed of section 5's unseen frames (Kinect noise, as in training).
UNSEEN_SEED = 777
#: A hand with fewer measured pixels than this (occluded, out of the image) is not in view.
IN_VIEW_PX = 500
#: The simulated hints of section 1 are the true hand moved by up to this many px.
HINT_MOTION_PX = 15.0
#: Section 6 lays each hand's silhouette on the body at up to this many places.
SURROUND_PROBES = 3


def _motions() -> dict:
    from train.hand_localiser import thesis_articulations

    return thesis_articulations(HIA, HELD_OUT) if HIA.is_dir() else {}


def test_set(loc: HandLocaliser, n: int, frames=None, blobs: bool = True) -> dict:
    """Section 1 of the module docstring (``frames``: these instead of the test set's
    renders; ``blobs=False`` leaves out the blob rules)."""
    from torchhand.geometry.camera import Camera
    from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands

    fr = frames if frames is not None else render_context_frames(n, TEST_SEED, ContextConfig(noise="stereo"),
                                                                 _motions(), name="test")
    n = len(fr.depth)
    ious, blob_ious, single_ious, e2, e3, conf, right, found, total = [], [], [], [], [], [], 0, 0, 0
    in_view, found_in_view, found_hinted, hinted_ious = 0, 0, 0, []
    rng = np.random.default_rng(TEST_SEED)
    for f in range(n):
        res = loc.locate(fr.depth[f].astype(np.float32))
        known = fr.labels[f] != IGNORE
        gt = np.isin(fr.labels[f], (1, 2)) & known
        if not gt.any():
            continue
        iou = lambda labels: float((np.isin(labels, (1, 2)) & gt).sum() / (np.isin(labels, (1, 2)) & known | gt).sum())
        ious.append(iou(res.labels))
        hands = np.isfinite(fr.joints_z[f]).all(1)
        # every hand in view hinted as a tracker would (its previous frame's fit), simulated
        hinted = loc.locate(fr.depth[f].astype(np.float32),
                            [_moved_hint(fr.depth[f], fr.labels[f] == 1 + k, rng) for k in range(2)
                             if hands[k] and (fr.labels[f] == 1 + k).sum() >= IN_VIEW_PX])
        hinted_ious.append(iou(hinted.labels))
        if hands.sum() == 1:
            single_ious.append(ious[-1])
        if hands.sum() == 1 and blobs:
            K = fr.K[f]
            cam = Camera.from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480)
            try:
                seg = segment_hands(fr.depth[f].astype(np.float32), cam, SegmentConfig(mode="blobs", far=4000.0))
                blob_ious.append(float((seg.mask & gt).sum() / ((seg.mask & known) | gt).sum()))
            except SegmentationError:
                blob_ious.append(0.0)
        for k, side in enumerate(("left", "right")):
            if not hands[k]:
                continue
            total += 1
            seen = int((fr.labels[f] == 1 + k).sum() >= IN_VIEW_PX)
            in_view += seen
            uv_gt, z_gt = fr.joints_uv[f, k], fr.joints_z[f, k]
            near = lambda hands: [h for h in hands if np.mean(np.linalg.norm(h.uv - uv_gt, axis=1)) < 60]
            found_hinted += seen * bool(near(hinted.hands))
            cand = near(res.hands)
            if not cand:
                continue
            h = cand[0]
            found += 1
            found_in_view += seen
            right += h.side == side
            e2.append(np.linalg.norm(h.uv - uv_gt, axis=1))
            conf.append(h.confidence)
            K = fr.K[f]
            p = lambda uv, z: np.stack([(uv[:, 0] - K[0, 2]) * z / K[0, 0], (uv[:, 1] - K[1, 2]) * z / K[1, 1], z], 1)
            e3.append(np.linalg.norm(p(h.uv, h.z) - p(uv_gt, z_gt), axis=1))
    e2, e3 = np.concatenate(e2), np.concatenate(e3)
    return {"frames": n, "hands": total, "hand_iou_mean": float(np.mean(ious)),
            "hand_iou_median": float(np.median(ious)), "frames_iou_ge_0_9": float(np.mean(np.array(ious) >= 0.9)),
            "blobs_hand_iou_mean": float(np.mean(blob_ious)) if blob_ious else None,
            "localiser_hand_iou_mean_one_hand_frames": float(np.mean(single_ious)) if single_ious else None,
            "keypoints_2d_median_px": float(np.median(e2)), "keypoints_2d_mean_px": float(np.mean(e2)),
            "keypoints_3d_median_mm": float(np.median(e3)), "keypoints_3d_mean_mm": float(np.mean(e3)),
            "handedness_accuracy": right / max(found, 1), "hands_found": found / max(total, 1),
            "hands_in_view": in_view, "hands_found_in_view": found_in_view / max(in_view, 1),
            "hands_found_in_view_with_hint": found_hinted / max(in_view, 1),
            "hand_iou_mean_with_hint": float(np.mean(hinted_ious)),
            "confidence_error_correlation": float(np.corrcoef(np.concatenate(conf), e2)[0, 1])}


def surround_in_context(fr) -> dict:
    """Section 6 of the module docstring, on the frames ``fr`` of section 1."""
    from types import SimpleNamespace

    from exp_real import laid_on_the_body
    from torchhand.scoring.metrics import FitCheckLimits, surrounded

    limit = FitCheckLimits().surrounded
    rng = np.random.default_rng(TEST_SEED)
    true, probes, high = [], [], []
    for f in range(len(fr.depth)):
        depth, labels, focal = fr.depth[f].astype(np.float32), fr.labels[f], float(fr.K[f][0, 0])
        models = np.isin(labels, (1, 2))
        for k in range(2):
            own = labels == 1 + k
            if own.sum() < IN_VIEW_PX:
                continue
            model = np.where(own, depth, 0)
            true.append(surrounded(own, model, models, depth, focal))
            if true[-1] > 0.3:
                high.append({"frame": f, "hand": ("left", "right")[k], "surround": true[-1]})
            probes += laid_on_the_body(model, SimpleNamespace(labels=labels, measured=depth), focal, rng,
                                       SURROUND_PROBES)
    true, probes = np.array(true, float), np.array(probes, float)
    true, probes = true[np.isfinite(true)], probes[np.isfinite(probes)]  # NaN: no surround to measure

    def stats(v, key):  # none when nothing was measured
        return ({f"{key}_median": float(np.median(v)), f"{key}_p95": float(np.percentile(v, 95)),
                 f"{key}_max": float(np.max(v)), f"{key}_flagged": float(np.mean(v > limit))} if len(v) else {})

    return {"limit": limit, "true_hands": len(true), **stats(true, "true_hands"), "true_hands_above_0_3": high,
            "probes": len(probes), **stats(probes, "probes")}


def _moved_hint(depth: np.ndarray, hand: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The hand's depth pixels moved by up to ``HINT_MOTION_PX`` px in a random direction."""
    a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0, HINT_MOTION_PX)
    M = np.float32([[1, 0, r * np.cos(a)], [0, 1, r * np.sin(a)]])
    h, w = depth.shape
    return cv2.warpAffine(np.where(hand, depth, 0).astype(np.float32), M, (w, h), flags=cv2.INTER_NEAREST)


def seen_and_unseen(loc: HandLocaliser, cache: Path, n: int) -> dict:
    """Section 5 of the module docstring."""
    from torchhand.salient.localiser_data import LocaliserFrames, load_localiser_frames

    seen = load_localiser_frames(cache)
    seen = LocaliserFrames(*(x[:n] for x in seen))
    unseen = render_context_frames(n, UNSEEN_SEED, ContextConfig(noise="kinect"), _motions(), name="unseen")
    keys = ("hand_iou_mean", "keypoints_2d_median_px", "handedness_accuracy", "hands_found_in_view")
    out = {"frames": n, "training_frames": str(cache)}
    for name, fr in (("seen", seen), ("unseen", unseen)):
        res = test_set(loc, n, fr, blobs=False)
        out[name] = {k: res[k] for k in keys}
    return out


def initialisation(n: int, compare_blobs: bool, loc: HandLocaliser) -> dict:
    """Section 2 of the module docstring, with the localiser ``loc``."""
    from torchhand.geometry.camera import Camera
    from torchhand.model.joints21 import standard_joints
    from torchhand.model.scene import Scene
    from torchhand.tracking.initialization import Initializer
    from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    cfg = ContextConfig(noise="stereo", p_two_hands=0.0, scale=(1.0, 1.0), finger_factor=(1.0, 1.0),
                        distance_mm=(350.0, 900.0))
    fr = render_context_frames(2 * n, TEST_SEED + 1, cfg, _motions(), name="init")
    keep = [f for f in range(len(fr.depth)) if np.isfinite(fr.joints_z[f, 1]).all()][:n]
    scene = Scene.from_names(["hand_right"])
    init = Initializer(Tracker(scene, TrackerConfig()))
    out = {}
    for mode in ("auto", "auto_true_joints") + (("blobs",) if compare_blobs else ()):
        errs, secs, fails = [], [], 0
        for f in keep:
            K = fr.K[f]
            cam = Camera.from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480)
            depth = fr.depth[f].astype(np.float32)
            t0 = time.perf_counter()
            try:
                segment = SegmentConfig(mode=mode.split("_")[0], far=4000.0)
                seg = segment_hands(depth, cam, segment, sides=("right",), localiser=loc)
                if mode == "auto_true_joints" and seg.located:  # the search given the true joints
                    seg = seg._replace(located=(seg.located[0]._replace(
                        uv=fr.joints_uv[f, 1].astype(np.float32), z=fr.joints_z[f, 1].astype(np.float32),
                        confidence=np.ones(21, np.float32)),) + tuple(seg.located[1:]))
                res = init(depth, cam, seg)
            except (SegmentationError, ValueError):
                fails += 1
                errs.append(float("inf"))
                continue
            secs.append(time.perf_counter() - t0)
            m = scene.models[0]
            with torch.no_grad():
                j = standard_joints(m(res.theta[None].float()), m)[0].numpy()
            uv, z = fr.joints_uv[f, 1], fr.joints_z[f, 1]
            gt = np.stack([(uv[:, 0] - K[0, 2]) * z / K[0, 0], (uv[:, 1] - K[1, 2]) * z / K[1, 1], z], 1)
            errs.append(float(np.linalg.norm(j - gt, axis=1).mean()))
            print(f"init ({mode}) frame {f}: {errs[-1]:.1f} mm, {secs[-1]:.1f} s", flush=True)
        e = np.array(errs)
        out[mode] = {"tries": len(keep), "success_le_10mm": float(np.mean(e <= 10.0)),
                     "median_mm": float(np.median(e)), "failed_to_segment": fails,
                     "seconds_per_hand_mean": float(np.mean(secs)) if secs else None}
    return out


def speed(loc: HandLocaliser, depth: np.ndarray, repeats: int = 30) -> dict:
    """Section 3 of the module docstring."""
    out = {}
    for name, shape in (("crop_128", (1, 1, 128, 128)), ("frame_160x120", (1, 1, 120, 160))):
        x = np.full(shape, 600.0, np.float32)
        ref = np.array([600.0], np.float32)
        loc.network(x, ref)
        t0 = time.perf_counter()
        for _ in range(repeats):
            loc.network(x, ref)
        out[f"network_{name}_ms"] = (time.perf_counter() - t0) / repeats * 1000
    out["network_fps_at_input_size"] = 1000.0 / out["network_crop_128_ms"]
    flip = loc.flip_test
    for loc.flip_test, key in ((flip, "locate_640x480_ms"), (not flip, f"locate_640x480_{'no_' * flip}flip_ms")):
        loc.locate(depth)
        t0 = time.perf_counter()
        for _ in range(10):
            loc.locate(depth)
        out[key] = (time.perf_counter() - t0) / 10 * 1000
    loc.flip_test = flip
    # the per-frame segmentation the tracker runs: the localiser's against the blob rules'
    from torchhand.geometry.camera import kinect_camera
    from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands

    for mode in ("auto", "blobs"):
        t0 = time.perf_counter()
        for _ in range(10):
            try:
                segment_hands(depth, kinect_camera(), SegmentConfig(mode=mode, far=4000.0), localiser=loc)
            except SegmentationError:
                pass
        out[f"segment_{mode}_ms"] = (time.perf_counter() - t0) / 10 * 1000
    return out


def sr305(loc: HandLocaliser, root: Path, figure: Path | None) -> dict:
    """Section 4 of the module docstring."""
    from torchhand.geometry.camera import Camera
    from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands

    cam = Camera.from_intrinsics(476.007, 476.007, 313.683, 242.755, 640, 480)
    rows, tiles = [], []
    for rec in sorted(p for p in root.iterdir() if p.is_dir()):
        for png in sorted(rec.glob("*.png"), key=lambda p: int(p.stem)):
            depth = cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.float32) / 8.0
            try:
                seg = segment_hands(depth, cam, SegmentConfig(), sides=("right",), localiser=loc)
            except SegmentationError as err:
                rows.append({"frame": f"{rec.name}/{png.stem}", "error": str(err)})
                continue
            h = seg.located[0] if seg.located else None
            rows.append({"frame": f"{rec.name}/{png.stem}", "source": seg.source, "pixels": int(seg.mask.sum()),
                         "side": None if h is None else h.side, "score": None if h is None else h.score,
                         "handedness": None if h is None else h.handedness})
            if figure is not None:
                tiles.append(_tile(depth, seg, f"{rec.name[-6:]}/{png.stem}"))
    if figure is not None and tiles:
        cols = 5
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
        grid = np.concatenate([np.concatenate(tiles[r:r + cols], 1) for r in range(0, len(tiles), cols)], 0)
        figure.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(figure), grid)
    return {"frames": len(rows), "found_by_localiser": sum(r.get("source") == "localiser" for r in rows),
            "right_hand": sum(r.get("side") == "right" for r in rows), "per_frame": rows}


def _tile(depth: np.ndarray, seg, label: str, size: int = 240) -> np.ndarray:
    from torchhand.app.drawing import draw_skeleton

    v = np.clip((depth - 300) / 1200 * 255, 0, 255).astype(np.uint8)
    img = cv2.cvtColor(255 - v, cv2.COLOR_GRAY2BGR)
    img[depth == 0] = 0
    if seg.labels is not None:
        body = seg.labels == 3
        img[body] = (0.5 * img[body] + [110, 40, 0]).astype(np.uint8)
    img[seg.mask] = (0.4 * img[seg.mask] + [0, 150, 0]).astype(np.uint8)
    for h in seg.located:  # the standard 21 joints share the 21-keypoint skeleton's order
        draw_skeleton(img, h.uv)
    img = cv2.resize(img, (size * 4 // 3, size))
    cv2.putText(img, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--init-frames", type=int, default=30)
    ap.add_argument("--compare-blobs", action="store_true", help="also initialise with the blob rules' seeds")
    ap.add_argument("--sr305", type=Path, default=REPO.parent / "shared" / "data" / "real" / "sr305")
    ap.add_argument("--figure", type=Path, help="the SR305 frames' classes and joints, one PNG")
    ap.add_argument("--weights", type=Path, help="an .onnx localiser (default: the shipped one)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--flip-test", action="store_true", help="the localiser with its test-time flip")
    ap.add_argument("--seen", type=Path, help="a training cache's train.npz: section 5 on its first --seen-frames")
    ap.add_argument("--seen-frames", type=int, default=160)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    loc = HandLocaliser.load(args.weights, threads=args.threads, flip_test=args.flip_test)
    frames = render_context_frames(args.frames, TEST_SEED, ContextConfig(noise="stereo"), _motions(), name="test")
    out = {"flip_test": loc.flip_test, "test_set": test_set(loc, args.frames, frames)}
    print(json.dumps(out["test_set"], indent=2), flush=True)
    out["surround"] = surround_in_context(frames)
    print(out["surround"], flush=True)
    if args.seen is not None:
        out["seen_and_unseen"] = seen_and_unseen(loc, args.seen, args.seen_frames)
        print(out["seen_and_unseen"], flush=True)
    if args.sr305.is_dir():
        out["sr305"] = sr305(loc, args.sr305, args.figure)
        print({k: v for k, v in out["sr305"].items() if k != "per_frame"}, flush=True)
    frame = render_context_frames(1, TEST_SEED + 2, ContextConfig(noise="stereo"), progress=False).depth[0]
    out["speed"] = speed(loc, frame.astype(np.float32))
    print(out["speed"], flush=True)
    if args.init_frames > 0:
        out["initialisation"] = initialisation(args.init_frames, args.compare_blobs, loc)
        print(out["initialisation"], flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
