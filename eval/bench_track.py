"""Tracking speed at 640x480 (kinect-noise renders of thesis motions).

    python eval/bench_track.py --hia-root ../shared/data/hands_in_action --json out/bench_track.json

Measurements, side by side in one run:
- ``one_hand``: seconds per frame for sequence 09 (one hand), ``--frames`` frames,
  at most ``--iterations`` iterations per frame;
- ``two_hands_object``: the same for sequence 16 (two hands and the ball);
- ``caps``: both scenes again with the iteration caps of ``--caps`` (speed against
  accuracy), and per scene the fastest cap within the accuracy targets (mean error
  <= 3 px and <= 6 mm, no frame above 20 mm); ``seconds_per_frame_after_first``
  leaves out frame 0, which has its own budget (``first_frame_iterations``);
- ``batched_vs_sequential``: 8 windows of sequence 12 (one hand), tracked one after
  another and then as one batch; frames per second of both and their ratio
  (``batched_speedup``).
- ``backends``: for both scenes at ``--compare-cap`` iterations per frame, the same frames
  tracked with each of ``--backends`` (renders and neighbour searches switched together:
  ``warp`` uses Warp kernels for both, ``open3d`` open3d's ray casting with scipy's
  KD-tree and distance transform); ``track_speedup_vs_open3d`` per scene is the ratio of
  their seconds per frame after frame 0.
- ``energies``: for both scenes at ``--iterations``, the same frames tracked with each
  energy of ``--energies``; ``time_vs_first`` is each one's seconds per frame after
  frame 0 over the first's (the default LO+F against the thesis' LO).
Accuracy (mean keypoint error) is reported next to each timing. ``--device cuda`` runs
the Warp backends on the GPU (open3d stays on the CPU).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from _common import machine, set_threads, write_json
from torchhand.data.synth import thesis_motion, write_synthetic_sequence
from torchhand.data.layout import OutputLayout, SequenceLayout
from torchhand.scoring.sequences import evaluate_sequence
from torchhand.app.runner import TrackOptions, track_sequences
from torchhand.tracking.tracker import TrackerConfig


def render(hia_root, seq, start, frames, out):
    fr = thesis_motion(hia_root, seq, slice(start, start + frames), dtype=torch.float32)
    fr.name = f"hia_{seq}_{start}"
    return write_synthetic_sequence(fr, out, noise="kinect", seed=start, rgb=False, progress=False)


def timed_track(roots, out, cfg, device="cpu"):
    """(wall seconds of the whole call, seconds spent tracking frames) — the second
    excludes loading models, reading nothing else and writing the outputs."""
    t0 = time.perf_counter()
    summaries = track_sequences(roots, out, TrackOptions(cfg, device=device), force=True, progress=False)
    wall = time.perf_counter() - t0
    log = json.loads(OutputLayout(summaries[0]["out"]).track_log.read_text())
    return wall, sum(f["seconds"] for f in log["frames"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--caps", default="1,2,3,5", help="comma-separated iteration caps for the speed-accuracy sweep ('' skips it)")
    ap.add_argument("--backends", default="warp,open3d", help="backends compared at --compare-cap ('' skips it)")
    ap.add_argument("--compare-cap", type=int, default=2, help="iterations per frame of the backend comparison")
    ap.add_argument("--device", default="cpu", help="torch device of the tracking (cpu or cuda)")
    ap.add_argument("--energies", default="LO,LO+F", help="energies compared at --iterations ('' skips it)")
    ap.add_argument("--only-energies", action="store_true", help="measure the energies comparison only")
    ap.add_argument("--prediction", type=float, default=0.0, help="TrackerConfig.prediction (1: constant-velocity start)")
    ap.add_argument("--no-prediction-limiter", dest="prediction_limiter", action="store_false",
                    help="extrapolate the last step as it is (TrackerConfig.prediction_limiter=False)")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    cfg = TrackerConfig(metric="point-to-plane", max_iterations=args.iterations, first_frame_iterations=args.iterations,
                        prediction=args.prediction, prediction_limiter=args.prediction_limiter)
    result = {"frames": args.frames, "iterations": args.iterations, "metric": cfg.metric, "prediction": cfg.prediction,
              "prediction_limiter": cfg.prediction_limiter, "device": args.device, "backend": cfg.render_backend,
              **machine()}
    if args.device.startswith("cuda"):
        result["cuda_device"] = torch.cuda.get_device_name(torch.device(args.device))
    caps = [int(c) for c in args.caps.split(",") if c.strip()]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        result["caps"] = {}
        for key, seq in (("one_hand", "09"), ("two_hands_object", "16")):
            root = render(args.hia_root, seq, 0, args.frames, tmp / key)
            energies = [e for e in args.energies.split(",") if e.strip()]
            if energies:
                comp = result.setdefault("energies", {}).setdefault(key, {})
                for e in energies:
                    comp[e] = scored_run(root, tmp / f"{key}_{e}", replace(cfg, energy=e), args.device)
                first = comp[energies[0]]["seconds_per_frame_after_first"]
                comp["time_vs_first"] = {e: comp[e]["seconds_per_frame_after_first"] / first for e in energies}
            if args.only_energies:
                continue
            result[key] = {"sequence": seq, **scored_run(root, tmp / f"{key}_out", cfg, args.device)}
            sweep = [{"cap": c, **scored_run(root, tmp / f"{key}_cap{c}", replace(cfg, max_iterations=c), args.device)}
                     for c in caps]
            ok = [r for r in sweep + [{"cap": args.iterations, **result[key]}] if within_targets(r)]
            result["caps"][key] = {"runs": sweep, "fastest_within_targets": min(ok, key=lambda r: r["seconds_per_frame"])
                                   if ok else None}
            backends = [b for b in args.backends.split(",") if b.strip()]
            if backends:
                comp = result.setdefault("backends", {}).setdefault(key, {})
                for b in backends:
                    c = replace(cfg, max_iterations=args.compare_cap, backend=b)
                    comp[b] = scored_run(root, tmp / f"{key}_{b}", c, "cpu" if b == "open3d" else args.device)
                if "open3d" in comp and "warp" in comp:
                    comp["track_speedup_vs_open3d"] = (comp["open3d"]["seconds_per_frame_after_first"]
                                                       / comp["warp"]["seconds_per_frame_after_first"])
        if args.only_energies:
            write_json(args.json, result)
            return
        windows = [render(args.hia_root, "12", 80 * k, args.frames // 2, tmp / f"w{k}") for k in range(args.batch)]
        seq_secs = sum(timed_track([w], tmp / f"seq_out{k}", cfg, args.device)[1] for k, w in enumerate(windows))
        bat_secs = timed_track(windows, tmp / "batch_out", cfg, args.device)[1]
        n = args.batch * (args.frames // 2)
        result["batched_vs_sequential"] = {"sequences": args.batch, "frames_each": args.frames // 2,
                                           "sequential_fps": n / seq_secs, "batched_fps": n / bat_secs,
                                           "speedup": seq_secs / bat_secs}
        result["batched_speedup"] = seq_secs / bat_secs
    write_json(args.json, result)


def scored_run(root: Path, out: Path, cfg: TrackerConfig, device: str = "cpu") -> dict:
    """Track one rendered sequence and score it against its ground truth."""
    timed_track([root], out, replace(cfg, max_iterations=1, first_frame_iterations=1), device)  # warm-up
    wall, secs = timed_track([root], out, cfg, device)
    info = json.loads(SequenceLayout(root).info.read_text())
    n, tracked = info["frames"], out / info["name"]
    ev = evaluate_sequence(tracked, SequenceLayout(root).gt, with_penetration=False)
    log = json.loads(OutputLayout(tracked).track_log.read_text())
    after_first = sum(f["seconds"] for f in log["frames"][1:]) / max(n - 1, 1)
    return {"seconds_per_frame": secs / n, "seconds_per_frame_with_io": wall / n,
            "seconds_per_frame_after_first": after_first,
            "iterations_per_frame": sum(f["iterations"] for f in log["frames"]) / n,
            "mean_mm": ev["mean_mm"], "mean_px": ev["thesis_mean_px"], "worst_frame_mm": max(ev["per_frame"]["mm"])}


def within_targets(run: dict) -> bool:
    return run["mean_px"] <= 3.0 and run["mean_mm"] <= 6.0 and run["worst_frame_mm"] <= 20.0


if __name__ == "__main__":
    main()
