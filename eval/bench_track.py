"""Tracking speed at 640x480 (kinect-noise renders of thesis motions).

    python eval/bench_track.py --hia-root ../shared/data/hands_in_action --json out/bench_track.json

Three measurements, side by side in one run:
- ``one_hand``: seconds per frame for sequence 09 (one hand), ``--frames`` frames;
- ``two_hands_object``: seconds per frame for sequence 16 (two hands and the ball);
- ``batched_vs_sequential``: 8 windows of sequence 12 (one hand), tracked one after
  another and then as one batch; frames per second of both and their ratio.
Accuracy (mean keypoint error) is reported next to each timing.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from _common import machine, set_threads, write_json
from torchhand.data.synth import thesis_motion, write_synthetic_sequence
from torchhand.evaluation import evaluate_sequence
from torchhand.tracker import TrackerConfig, track_sequences


def render(hia_root, seq, start, frames, out):
    fr = thesis_motion(hia_root, seq, slice(start, start + frames), dtype=torch.float32)
    fr.name = f"hia_{seq}_{start}"
    return write_synthetic_sequence(fr, out, noise="kinect", seed=start, rgb=False, progress=False)


def timed_track(roots, out, cfg):
    """(wall seconds of the whole call, seconds spent tracking frames) — the second
    excludes loading models, reading nothing else and writing the outputs."""
    t0 = time.perf_counter()
    summaries = track_sequences(roots, out, cfg, force=True, progress=False)
    wall = time.perf_counter() - t0
    log = json.loads((Path(summaries[0]["out"]) / "track_log.json").read_text())
    return wall, sum(f["seconds"] for f in log["frames"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    cfg = TrackerConfig(metric="point-to-plane", max_iterations=args.iterations, first_frame_iterations=args.iterations)
    result = {"frames": args.frames, "iterations": args.iterations, "metric": cfg.metric, **machine()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for key, seq in (("one_hand", "09"), ("two_hands_object", "16")):
            root = render(args.hia_root, seq, 0, args.frames, tmp / key)
            wall, secs = timed_track([root], tmp / f"{key}_out", cfg)
            ev = evaluate_sequence(tmp / f"{key}_out" / f"hia_{seq}_0", root / "gt", with_penetration=False)
            result[key] = {"sequence": seq, "seconds_per_frame": secs / args.frames,
                           "seconds_per_frame_with_io": wall / args.frames, "mean_mm": ev["mean_mm"],
                           "mean_px": ev["mean_px"]}
        windows = [render(args.hia_root, "12", 80 * k, args.frames // 2, tmp / f"w{k}") for k in range(args.batch)]
        seq_secs = sum(timed_track([w], tmp / f"seq_out{k}", cfg)[1] for k, w in enumerate(windows))
        bat_secs = timed_track(windows, tmp / "batch_out", cfg)[1]
        n = args.batch * (args.frames // 2)
        result["batched_vs_sequential"] = {"sequences": args.batch, "frames_each": args.frames // 2,
                                           "sequential_fps": n / seq_secs, "batched_fps": n / bat_secs,
                                           "speedup": seq_secs / bat_secs}
    write_json(args.json, result)


if __name__ == "__main__":
    main()
