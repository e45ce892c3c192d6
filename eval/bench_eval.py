"""Evaluation speed: 10 sequences x 200 frames scored in one call.

    python eval/bench_eval.py --json out/bench_eval.json [--sequences 10] [--frames 200] [--workers 2]

Ground truth is built from the demo motion (two hands and the ball, looped), predictions
are perturbed copies; both in the gt/ layout. Times ``evaluate_many`` on the keypoint
measures for all pairs, and the penetration measures per frame on one sequence.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _common import demo_scene, machine, set_threads, write_json
from torchhand.data.layout import Poses, SequenceLayout, write_poses
from torchhand.app.scaleout import evaluate_pairs
from torchhand.scoring.sequences import evaluate_many
from torchhand.model.scene import Scene


def make_pair(root: Path, k: int, scene: Scene, theta: torch.Tensor, cam, frames: int):
    rng = np.random.default_rng(k)
    idx = np.arange(frames) % len(theta)
    th = theta[idx].double().numpy()
    pred = th + rng.normal(0, 0.01, th.shape)
    seq = SequenceLayout(root / f"seq{k:02d}")
    folders = (seq.root / "pred", seq.gt.root)  # a prediction beside the sequence's gt/
    for folder, t in zip(folders, (pred, th)):
        with torch.no_grad():
            kp = scene(torch.as_tensor(t, dtype=torch.float32)).keypoints
        poses = Poses(t, cam.to_camera(kp).numpy()[:, None], cam.project(kp).numpy()[:, None], list(scene.names),
                      scene.dof_names, scene.keypoint_names)
        write_poses(folder, poses)
    return folders


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--sequences", type=int, default=10)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--penetration-frames", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    names, theta, scene, cam = demo_scene()
    result = {"sequences": args.sequences, "frames": args.frames, "workers": args.workers, **machine()}
    with tempfile.TemporaryDirectory() as tmp:
        pairs = [make_pair(Path(tmp), k, scene, theta, cam, args.frames) for k in range(args.sequences)]
        t0 = time.perf_counter()
        evaluate_pairs(pairs, workers=args.workers, with_penetration=False, progress=False)
        result["keypoints_seconds"] = time.perf_counter() - t0
        # Penetration (fcl triangle pairs + open3d depth per frame) is far slower: timed
        # on --penetration-frames frames of one sequence and reported per frame.
        pen = make_pair(Path(tmp) / "pen", 99, scene, theta, cam, args.penetration_frames)
        t0 = time.perf_counter()
        evaluate_many([pen], with_penetration=True, progress=False)
        result["penetration_ms_per_frame"] = 1000 * (time.perf_counter() - t0) / args.penetration_frames
    write_json(args.json, result)


if __name__ == "__main__":
    main()
