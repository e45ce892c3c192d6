"""Salient point detectors: precision-recall on held-out renders, ONNX Runtime speed, parity.

    python eval/eval_salient.py --json out/eval_salient.json [--plot out/salient_pr.png]
        [--hia-root ../shared/data/hands_in_action] [--weights models/salient_fingertips.pt]
        [--onnx models/salient_fingertips.onnx]
    python eval/eval_salient.py --modality colour --json out/eval_nails.json [--plot ...]

``--modality colour`` evaluates the nail detector (``models/salient_nails_rgb.pt``) on
shaded colour renders seen by the ring of eight cameras (textured backgrounds the
training never drew), once clean and once with Ballan's structural noise on every
frame; ``ap`` is over both, ``ap_clean`` and ``ap_circles`` over each.

Held-out frames (640x480, Kinect noise, random backgrounds) are the thesis sequences of
the training's validation split (not used for training) and random poses of two hands
and an object with a seed no training set uses. A detection is a true positive within
10 px of a not yet matched visible fingertip (PASCAL VOC protocol, all-points
interpolated AP; see ``docs/salient.md``). Speed is the ONNX Runtime session alone
(``intra_op_num_threads`` = --threads, and one thread next to it) and the full ``detect``
call, on a rendered frame.
Writes {"ap": a, "ort_fps_320x240": f, "ort_fps_640x480": g, "max_abs_diff": d, ...}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from _common import machine, median_seconds, set_threads, write_json
from torchhand.data.synth import random_poses, thesis_motion
from torchhand.io.thesis import sequence_models
from torchhand.app.options import NAIL_SCORE
from torchhand.salient import SalientDetector, average_precision
from torchhand.salient.training_data import concat_frames, render_salient_frames, visible_mm2
from torchhand.salient.detector import MODALITIES, shipped_weights

REPO = Path(__file__).resolve().parents[1]
VAL_SEQUENCES = ["03", "10", "20"]  # the validation split of train/salient_detector.py


def held_out_frames(hia_root: Path, sequences, per_sequence: int, random_frames: int, seed: int,
                    modality: str = "depth", circles: float = 0.0):
    kw = {"modality": modality, "circles": circles} if modality == "colour" else {}
    parts = []
    for k, seq in enumerate(sequences):
        _, bounds = sequence_models(hia_root, seq)
        step = max(1, bounds.total_aligned // per_sequence)
        # Offset by half a step from the training-time validation frames.
        frames = thesis_motion(hia_root, seq, frames=slice(step // 2, step // 2 + step * per_sequence, step),
                               dtype=torch.float32)
        parts.append(render_salient_frames(frames, seed=seed + k, progress=True, **kw))
    if random_frames:
        frames = random_poses(["hand_right", "hand_left", "ball"], random_frames, seed=seed + 100,
                              distance=(350.0, 850.0), dtype=torch.float32)
        parts.append(render_salient_frames(frames, seed=seed + 100, progress=True, **kw))
    return concat_frames(parts)


def operating_point(pr, precision: float = 0.9) -> dict:
    """The detection threshold with the highest recall at ``precision`` or better: the
    confidence of the last counted detection where the curve still reaches it."""
    ok = np.nonzero(pr.precision >= precision)[0]
    if not len(ok):
        return {"precision": precision, "score": None, "recall": 0.0}
    k = int(ok[-1])
    return {"precision": precision, "score": float(pr.scores[k]), "recall": float(pr.recall[k])}


def at_score(pr, score: float) -> dict:
    """Precision and recall of the detections with confidence ``score`` or more."""
    k = int(np.searchsorted(-pr.scores, -score, side="right"))  # scores are sorted decreasing
    if k == 0:
        return {"score": score, "precision": None, "recall": 0.0}
    return {"score": score, "precision": float(pr.precision[k - 1]), "recall": float(pr.recall[k - 1])}


def net_input(image: np.ndarray) -> np.ndarray:
    """(1, C, H, W) float32 network input of one (H, W) depth or (H, W, 3) RGB frame."""
    x = image.astype(np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None] if x.ndim == 3 else x[None, None])


def pr_of(detector, data, radius: float):
    uv, sc, gt, ign = [], [], [], []
    vis = visible_mm2(data)
    for f in range(len(data.image)):
        d = detector.detect(data.image[f])
        uv.append(d.uv.cpu().numpy())
        sc.append(d.score.cpu().numpy())
        a = data.area_mm2[f]
        gt.append(data.uv[f][a >= vis])
        ign.append(data.uv[f][(a > 0) & (a < vis)])
    return (average_precision(uv, sc, gt, radius=radius, gt_ignore=ign),
            average_precision(uv, sc, [np.concatenate([g, i]) for g, i in zip(gt, ign)], radius=radius))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--plot", type=Path, help="precision-recall curve (PNG)")
    ap.add_argument("--hia-root", type=Path, default=REPO.parent / "shared" / "data" / "hands_in_action")
    ap.add_argument("--modality", choices=sorted(MODALITIES), default="depth",
                    help="depth: fingertips on depth; colour: nails on colour")
    ap.add_argument("--weights", type=Path, help="default: the shipped network of --modality")
    ap.add_argument("--onnx", type=Path, help="default: the shipped export of --modality")
    ap.add_argument("--per-sequence", type=int, default=40, help="frames per held-out thesis sequence")
    ap.add_argument("--random-frames", type=int, default=80)
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--radius", type=float, default=10.0, help="true-positive radius (px)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=200, help="timed runs per speed measurement")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    weights = args.weights or shipped_weights(args.modality, onnx=False)
    onnx = args.onnx or shipped_weights(args.modality, onnx=True)

    held_out = (args.hia_root, VAL_SEQUENCES, args.per_sequence, args.random_frames, args.seed, args.modality)
    data = held_out_frames(*held_out)
    extra = {}
    det = SalientDetector.load(weights)
    ort_det = SalientDetector.load_onnx(onnx, threads=args.threads)
    if det.modality != args.modality or ort_det.modality != args.modality:
        raise SystemExit(f"--modality {args.modality}: {weights} is a {det.modality} network and {onnx} a "
                         f"{ort_det.modality} graph")
    if args.modality == "colour":
        noisy = held_out_frames(*held_out[:4], args.seed + 500, "colour", circles=1.0)
        extra["ap_clean"] = pr_of(det, data, args.radius)[0].ap
        extra["ap_circles"] = pr_of(det, noisy, args.radius)[0].ap
        data = concat_frames([data, noisy])
    t0 = time.perf_counter()
    pr, pr_strict = pr_of(det, data, args.radius)
    t_eval = time.perf_counter() - t0
    pr_ort, _ = pr_of(ort_det, data, args.radius)

    # Speed on a rendered frame (640x480) and its 2x-subsampled version (320x240).
    frame = data.image[0].astype(np.float32)
    speed = {}
    one = SalientDetector.load_onnx(onnx, threads=1) if args.threads != 1 else None
    for name, img in (("320x240", frame[::2, ::2]), ("640x480", frame)):
        x = net_input(img)
        t = median_seconds(lambda: ort_det.run(x), args.repeats, warmup=10)
        td = median_seconds(lambda: ort_det.detect(img), max(1, args.repeats // 2), warmup=5)
        tt = median_seconds(lambda: det.detect(img), max(1, args.repeats // 4), warmup=3)
        speed[f"ort_fps_{name}"] = 1.0 / t
        speed[f"ort_detect_fps_{name}"] = 1.0 / td
        speed[f"torch_detect_fps_{name}"] = 1.0 / tt
        if one is not None:  # the session alone on one core, side by side
            speed[f"ort_fps_{name}_1thread"] = 1.0 / median_seconds(lambda: one.run(x), args.repeats, warmup=10)

    # Parity on a size the graph was not exported with (export: 240x320).
    x = net_input(frame[100:300, 150:446])  # 200x296
    with torch.no_grad():
        ref = det.net(torch.from_numpy(x))
    got = ort_det.run(x)
    diff = max(float((a - b).abs().max()) for a, b in zip(ref, got))

    n_vis = int(sum((a >= visible_mm2(data)).sum() for a in data.area_mm2))
    result = {"ap": pr.ap, "ort_fps_320x240": speed["ort_fps_320x240"], "ort_fps_640x480": speed["ort_fps_640x480"],
              "max_abs_diff": diff, "ap_onnx": pr_ort.ap, "ap_all_partial_as_gt": pr_strict.ap, **extra,
              "operating_points": [operating_point(pr, q) for q in (0.9, 0.95)],
              **({"at_nail_score": at_score(pr, NAIL_SCORE)} if args.modality == "colour" else {}),
              "modality": args.modality,
              **{k: v for k, v in speed.items() if k not in ("ort_fps_320x240", "ort_fps_640x480")},
              "parity_input": [200, 296], "radius_px": args.radius, "frames": int(len(data.image)),
              "visible_fingertips": n_vis, "sequences": VAL_SEQUENCES, "random_frames": args.random_frames,
              "seed": args.seed, "eval_seconds_torch": t_eval, "weights": str(weights), **machine()}
    if args.plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(4, 4))
        ax.plot(pr.recall, pr.precision, label=f"AP {pr.ap:.3f}")
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_title(f"{'nails (colour)' if args.modality == 'colour' else 'fingertips'}, {args.radius:g} px")
        ax.legend(loc="lower left")
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=100, bbox_inches="tight")
    write_json(args.json, result)


if __name__ == "__main__":
    main()
