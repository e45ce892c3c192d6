"""The automatic initialisation on renders of the thesis motions (docs/results.md).

    python eval/exp_init.py --hia-root ../shared/data/hands_in_action --tries 20 --frames 20 --work out/exp --json out/exp_init.json

Every shared sequence whose scene is hands only (the initialisation places hands;
sequences with objects need ``init_pose.json`` and are listed as skipped) is rendered
with the kinect noise model (frames 0..F-1, the same renders as ``exp_tracking.py lo``).

1. Initialisation: frame 0 is segmented automatically (as many hands as the scene has)
   and initialised ``--tries`` times, try k with ``InitConfig(seed=k, restarts=R)`` (the
   swarms' random draws; ``--restarts``, default the library's); each try's error is the
   mean distance of its keypoints (every hand's 21) to the ground truth's, and its
   ``costs`` entry its depth discrepancy at full resolution (what the search ranks by).
   A try succeeds within ``--success-mm`` (10 mm).
2. Tracking: a copy of the sequence without ``init_pose.json`` and without ``gt/`` is
   tracked with the CLI defaults (so frame 0 is initialised automatically, seed 0, with
   ``--restarts``) and
   scored against ``gt/`` (mean px / mm over the frames, worst frame).

Writes the per-sequence success rates and errors, the pooled success rate, and the
tracking scores to ``--json``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, set_threads, write_json  # noqa: E402
from exp_tracking import render_sequences  # noqa: E402

from torchhand.app.runner import TrackOptions, track_sequences  # noqa: E402
from torchhand.data.layout import SequenceLayout, read_depth, read_poses, read_sequence_info  # noqa: E402
from torchhand.io.thesis import sequence_models  # noqa: E402
from torchhand.model.scene import Scene  # noqa: E402
from torchhand.scoring.sequences import evaluate_sequence  # noqa: E402
from torchhand.tracking.initialization import InitConfig, Initializer  # noqa: E402
from torchhand.tracking.segmentation import SegmentConfig, segment_hands  # noqa: E402
from torchhand.tracking.tracker import Tracker, TrackerConfig  # noqa: E402


def init_tries(folder: Path, tries: int, success_mm: float, restarts: int) -> dict:
    """``tries`` seeded initialisations of a rendered sequence's frame 0, scored."""
    info = read_sequence_info(folder)
    scene = Scene.from_names(info.models)
    tracker = Tracker(scene, TrackerConfig())
    cam = info.cameras[0]
    path = SequenceLayout(folder).depth(0)
    depth = read_depth(path, info.depth_unit_mm)
    seg = segment_hands(depth, cam, SegmentConfig(hands=len(scene.models)), frame=str(path))
    truth = torch.as_tensor(read_poses(SequenceLayout(folder).gt).keypoints_3d[0], dtype=torch.float32)  # (K, 3)
    errors, seconds, costs = [], [], []
    initializer = Initializer(tracker)
    for k in range(tries):
        initializer.config = InitConfig(seed=k, restarts=restarts)
        res = initializer(depth, cam, seg)
        costs.append(round(res.cost, 4))
        with torch.no_grad():
            kp = scene(res.theta[None]).keypoints[0]
        errors.append(float((kp - truth).norm(dim=-1).mean()))
        seconds.append(res.seconds)
    errors_a = np.asarray(errors)
    return {"models": list(info.models), "tries": tries, "success_rate": float((errors_a <= success_mm).mean()),
            "errors_mm": [round(e, 2) for e in errors], "costs": costs, "median_mm": float(np.median(errors_a)),
            "worst_mm": float(errors_a.max()), "seconds_per_try": float(np.mean(seconds)),
            "seconds_per_hand": float(np.mean(seconds) / len(scene.models))}


def without_init_pose(folder: Path, work: Path) -> Path:
    """A copy of a rendered sequence without ``init_pose.json`` and ``gt/`` (what a user
    with only the depth has)."""
    target = work / f"{folder.name}_noinit"
    if target.exists():
        shutil.rmtree(target)
    layout = SequenceLayout(folder)
    shutil.copytree(folder, target, ignore=shutil.ignore_patterns(layout.gt.root.name, layout.init_pose.name))
    return target


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--sequences", help="comma-separated (default: every hands-only sequence with MOTION files)")
    ap.add_argument("--tries", type=int, default=20)
    ap.add_argument("--frames", type=int, default=20, help="frames tracked after the initialisation")
    ap.add_argument("--success-mm", type=float, default=10.0)
    ap.add_argument("--work", type=Path, default=Path("out/exp"))
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--restarts", type=int, default=InitConfig().restarts,
                    help="independent swarms per initialisation (InitConfig.restarts)")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    seqs = args.sequences.split(",") if args.sequences else sorted(p.name for p in (args.hia_root / "Configs").iterdir())
    skipped = {}
    hands_only = []
    for s in seqs:
        names = sequence_models(args.hia_root, s)[0]
        if any("Hand" not in n for n in names):
            skipped[s] = f"objects in the scene ({', '.join(names)}): the initialisation places hands only"
        else:
            hands_only.append(s)
    folders = render_sequences(args.hia_root, hands_only, args.frames, args.work)
    for s in hands_only:
        if s not in folders:
            skipped[s] = "no MOTION files"
    results = {}
    for s, folder in folders.items():
        t0 = time.perf_counter()
        r = init_tries(folder, args.tries, args.success_mm, args.restarts)
        plain = without_init_pose(folder, args.work)
        out = args.work / "tracked_noinit"
        options = TrackOptions(TrackerConfig(), init_config=InitConfig(restarts=args.restarts))
        summary = track_sequences([plain], out, options, force=True, progress=False)[0]
        if summary["status"] != "ok":
            raise RuntimeError(f"sequence {s}: tracking failed: {summary['error']}")
        score = evaluate_sequence(summary["out"], SequenceLayout(folder).gt, with_penetration=False)
        r["tracking"] = {"frames": score["frames"], "mean_px": score["thesis_mean_px"], "mean_mm": score["mean_mm"],
                         "worst_frame_mm": float(max(score["per_frame"]["mm"])),
                         "frame0_mm": float(score["per_frame"]["mm"][0])}
        r["seconds"] = time.perf_counter() - t0
        results[s] = r
        print(s, {k: v for k, v in r.items() if k not in ("errors_mm", "costs")}, flush=True)
    rates = [r["success_rate"] for r in results.values()]
    errors = np.concatenate([r["errors_mm"] for r in results.values()]) if results else np.zeros(0)
    result = {
        "experiment": "automatic initialisation on kinect renders of the thesis motions",
        "success_mm": args.success_mm, "tries_per_sequence": args.tries, "frames_tracked": args.frames,
        "restarts": args.restarts,
        "sequences": results, "skipped": skipped,
        "overall": {"success_rate": float((errors <= args.success_mm).mean()) if errors.size else float("nan"),
                    "worst_sequence_success_rate": min(rates) if rates else float("nan"),
                    "sequences_at_90pct": int(sum(r >= 0.9 for r in rates)), "sequences": len(rates),
                    "tracking_mean_px": float(np.mean([r["tracking"]["mean_px"] for r in results.values()])),
                    "tracking_mean_mm": float(np.mean([r["tracking"]["mean_mm"] for r in results.values()])),
                    "seconds_per_hand": float(np.mean([r["seconds_per_hand"] for r in results.values()]))},
        "machine": machine(),
    }
    write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
