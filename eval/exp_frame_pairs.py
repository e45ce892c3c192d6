"""Thesis Ch. 3's frame-pair benchmark: which silhouette distance estimates a hand pose best.

    python eval/exp_frame_pairs.py --hia-root ../shared/data/hands_in_action --json out/exp_frame_pairs.json

Pairs (thesis Sec. 3.5): from the shared motions of the sequences with hands only,
``--fraction`` of the frames are drawn as test frames (seeded); each makes a pair with
the frame 1, 5, 10 and 15 frames before it (the starting pose). The test frame's
silhouettes are rendered in ``--views`` cameras around the scene
(:func:`torchhand.data.synth.with_camera_ring`: the synthetic setup; noise-free). From
the starting pose the pose is estimated by silhouette fitting alone (Eq. 3.9-3.10):
at each of ``--iterations`` rounds the model is rendered in every view, the vertices on
its silhouette's boundary (with the image direction of their normals) are paired with
the test frame's contour by one distance of Sec. 3.4 (:mod:`torchhand.geometry.chamfer`:
CH, DCH-Thres with tau 22.5 deg signed and unsigned, DCH-Quant, DCH-Quant2, DCH-DT3 with
lambda 25 and 16 bins, and unsigned with 8 bins over 180 deg, the same bin width, as
colour edges need), and their reprojection errors are minimised (the library's
Levenberg-Marquardt): this is the tracker's edge term ``E``
(:mod:`torchhand.tracking.energies.edges`) with silhouettes for image edges, so the
distance that wins here is the one the term uses. The error is the mean distance of the
21 joints per hand to the truth (mm), per gap, as the thesis' Table 3.1; and the share
of pairs below each error (Fig. 3.2-3.4).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from tqdm import tqdm

from torchhand.data.synth import thesis_motion, with_camera_ring
from torchhand.geometry.chamfer import ChamferConfig, silhouette_contour
from torchhand.geometry.render import Renderer
from torchhand.io.thesis import FormatError, sequence_models
from torchhand.tracking.energies.edges import Edges
from torchhand.tracking.preprocess import ColourFrame
from torchhand.tracking.tracker import Tracker, TrackerConfig

GAPS = (1, 5, 10, 15)
#: the distances compared: (label, ChamferConfig)
DISTANCES = [("CH", ChamferConfig("CH")), ("DCH-Thres", ChamferConfig("DCH-Thres")),
             ("DCH-Thres (180)", ChamferConfig("DCH-Thres", signed=False)),
             ("DCH-Quant", ChamferConfig("DCH-Quant", bins=8)), ("DCH-Quant2", ChamferConfig("DCH-Quant2", bins=8)),
             ("DCH-DT3", ChamferConfig("DCH-DT3", bins=16, lam=25.0)),
             ("DCH-DT3 (180)", ChamferConfig("DCH-DT3", bins=8, lam=25.0, signed=False))]


def hand_sequences(hia_root) -> dict:
    """{sequence: frames} of the shared sequences whose models are hands only and whose
    motion is shared (held-out motions are skipped)."""
    out = {}
    for s in [f"{i:02d}" for i in range(1, 22)]:
        try:
            names, bounds = sequence_models(hia_root, s)
            if names and all("hand" in n.lower() for n in names):
                thesis_motion(hia_root, s, slice(0, 1))  # raises where the motion is held out
                out[s] = bounds.total_aligned
        except (FormatError, OSError):
            continue
    return out


def make_pairs(lengths: dict, fraction: float, seed: int, per_gap: int) -> list:
    """[(sequence, start, test, gap)]: test frames drawn per sequence, paired with the frame
    ``gap`` before; at most ``per_gap`` pairs per gap over all sequences (evenly drawn)."""
    g = np.random.default_rng(seed)
    pairs = []
    for gap in GAPS:
        cand = []
        for s, n in lengths.items():
            frames = np.arange(max(GAPS), n)
            k = max(int(round(fraction * n)), 1)
            cand += [(s, int(t) - gap, int(t), gap) for t in g.choice(frames, size=min(k, len(frames)), replace=False)]
        idx = g.permutation(len(cand))[:per_gap]
        pairs += [cand[i] for i in sorted(idx)]
    return pairs


def fit_silhouettes(scene, cams, start, targets, config: ChamferConfig, iterations: int = 12,
                    lm_iterations: int = 3, per_view: int = 400) -> torch.Tensor:
    """The pose fitted to the target silhouettes from ``start`` (module docstring): the
    tracker's edge term (:class:`~torchhand.tracking.energies.edges.Edges`, with the
    distance ``config`` and no outlier cut) with the silhouette contours as the image
    edges, alone, solved by the tracker over every view."""
    frames = [ColourFrame(np.zeros((c.height, c.width), np.uint8), torch.as_tensor(pix, dtype=torch.int64),
                          torch.as_tensor(phi, dtype=start.dtype)) for c, (pix, phi) in zip(cams, targets)]
    cfg = TrackerConfig(energy="E", inner_iterations=lm_iterations, step_retries=2, min_joint_motion=0.0)
    tracker = Tracker(scene, cfg, [Edges(config, max_points=per_view, sigma=None, contours="silhouette")])
    return tracker.solve(start, start, [None] * len(cams), list(cams), iterations, colours=frames,
                         views=len(cams)).theta


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hia-root", type=Path, required=True)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--fraction", type=float, default=0.1, help="share of each sequence's frames drawn as test frames")
    p.add_argument("--pairs-per-gap", type=int, default=20, help="at most this many pairs per gap")
    p.add_argument("--iterations", type=int, default=12, help="correspondence rounds per pair")
    p.add_argument("--only", default=None, help="comma-separated distance labels (default: all)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    lengths = hand_sequences(args.hia_root)
    if not lengths:
        p.error(f"{args.hia_root}: no sequence with hands only and a shared motion")
    pairs = make_pairs(lengths, args.fraction, args.seed, args.pairs_per_gap)
    distances = [(k, c) for k, c in DISTANCES if args.only is None or k in args.only.split(",")]
    rows = {k: [] for k, _ in distances}
    seconds = {k: 0.0 for k, _ in distances}
    scenes = {}
    for s, start, test, gap in tqdm(pairs, desc="frame pairs", unit="pair"):
        if s not in scenes:  # each sequence's frames of its pairs, loaded once; one rig around its first test frame
            lo = min(a for q, a, _, _ in pairs if q == s)
            hi = max(b for q, _, b, _ in pairs if q == s)
            motion = thesis_motion(args.hia_root, s, slice(lo, hi + 1), dtype=torch.float64)
            scene = motion.scene
            ring = with_camera_ring(dataclasses.replace(motion, theta=motion.theta[test - lo : test - lo + 1]),
                                    args.views)
            scenes[s] = (scene, Renderer(scene.faces, scene.face_model_id, scene.face_bone_id),
                         [c.to(dtype=torch.float64) for c in ring.cameras], motion.theta, lo)
        scene, renderer, cams, theta, lo = scenes[s]
        first = SimpleNamespace(theta=theta[start - lo : start - lo + 1])
        last = SimpleNamespace(theta=theta[test - lo : test - lo + 1])
        with torch.no_grad():
            truth = scene(last.theta)
            targets = [silhouette_contour((renderer(truth.vertices, c).face_id[0] >= 0).numpy()) for c in cams]
        for label, cfg in distances:
            t0 = time.perf_counter()
            est = fit_silhouettes(scene, cams, first.theta, targets, cfg, args.iterations)
            seconds[label] += time.perf_counter() - t0
            with torch.no_grad():
                err = float((scene(est).keypoints - truth.keypoints).norm(dim=-1).mean())
                start_err = float((scene(first.theta).keypoints - truth.keypoints).norm(dim=-1).mean())
            rows[label].append({"sequence": s, "start": start, "test": test, "gap": gap, "error_mm": err,
                                "start_error_mm": start_err})
    table = {}
    for label, _ in distances:
        errs = {gap: [r["error_mm"] for r in rows[label] if r["gap"] == gap] for gap in GAPS}
        every = [e for v in errs.values() for e in v]
        table[label] = {**{f"gap{g}": [float(np.mean(v)), float(np.std(v))] for g, v in errs.items() if v},
                        "all": [float(np.mean(every)), float(np.std(every))],
                        "seconds_per_pair": seconds[label] / max(len(rows[label]), 1),
                        "below_mm": {str(t): float(np.mean(np.asarray(every) < t)) for t in (2, 5, 10, 15, 20)}}
    start = {gap: float(np.mean([r["start_error_mm"] for r in next(iter(rows.values())) if r["gap"] == gap]))
             for gap in GAPS}
    best = min(table, key=lambda k: table[k]["all"][0])
    result = {"sequences": sorted(lengths), "views": args.views, "pairs": len(pairs), "iterations": args.iterations,
              "start_error_mm": start, "table": table, "best": best, "rows": rows}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(markdown(result))
    return 0


def _start(result: dict, gap: int) -> float:
    s = result["start_error_mm"]
    return s[gap] if gap in s else s[str(gap)]  # int keys in memory, strings in the JSON


def markdown(result: dict) -> str:
    """Table 3.1's analogue from the JSON of a run."""
    head = "| distance | " + " | ".join(f"gap {g} (mm)" for g in GAPS) + " | all (mm) | s per pair |"
    lines = [head, "|" + "---|" * (len(GAPS) + 3),
             "| (starting pose) | " + " | ".join(f"{_start(result, g):.1f}" for g in GAPS) + " | | |"]
    for label, t in result["table"].items():
        cells = [f"{t[f'gap{g}'][0]:.1f} ± {t[f'gap{g}'][1]:.1f}" if f"gap{g}" in t else "" for g in GAPS]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {t['all'][0]:.1f} ± {t['all'][1]:.1f} | "
                     f"{t['seconds_per_pair']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
