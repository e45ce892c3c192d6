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
- ``--profile``: instead of the above, both scenes at ``--profile-cap`` iterations per
  frame with the tracker's stage timers on (:mod:`torchhand.core.profiling`): per stage
  (preprocess, labels, render, each term's preparation, rows and rows+J, posing, the
  normal equations and solve, host syncs) its ms per frame after frame 0 and per outer
  iteration, and its floor: the stage's unavoidable arithmetic and memory traffic at this
  machine's single-thread matmul GFLOP/s and copy GB/s (measured at the start),
  ``max(flops / GFLOP/s, bytes / GB/s)``. ``fused`` in the JSON when ``--fused`` is given:
  the same with ``TrackerConfig.fused`` on, side by side; the ms per frame of each are
  medians over ``--repeats`` further unprofiled runs, torch and fused alternating.
  ``--hold-frames N`` (40 by default, 0 skips it): each scene tracked again at the
  profile's cap over its first N frames, scored (``<scene>_held_px``,
  ``<scene>_held_worst_mm``, ``<scene>_held_ms``): whether the cap's accuracy over the
  short profiled window holds over a longer one (a cap too low for the motion drifts
  off within a few dozen frames).
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
    ap.add_argument("--prediction", type=float, default=None,
                    help="TrackerConfig.prediction (0: the previous pose, 1: constant-velocity start; default: the "
                         "tracker's, 1 for these scenes)")
    ap.add_argument("--no-prediction-limiter", dest="prediction_limiter", action="store_false",
                    help="extrapolate the last step as it is (TrackerConfig.prediction_limiter=False)")
    ap.add_argument("--profile", action="store_true", help="time the tracker's stages against their floors")
    ap.add_argument("--profile-cap", type=int, default=1, help="iterations per frame of --profile")
    ap.add_argument("--scenes", default="one_hand,two_hands_object", help="scenes of --profile")
    ap.add_argument("--fused", action="store_true", help="--profile also with TrackerConfig.fused, side by side")
    ap.add_argument("--repeats", type=int, default=4, help="--profile: unprofiled runs per variant, alternating")
    ap.add_argument("--hold-frames", type=int, default=40,
                    help="--profile: also score each scene at the profile's cap over this many frames (0 skips it)")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    if args.profile:
        write_json(args.json, {"threads": args.threads, **machine(), **profile(args)})
        return
    cfg = TrackerConfig(metric="point-to-plane", max_iterations=args.iterations, first_frame_iterations=args.iterations,
                        prediction=args.prediction, prediction_limiter=args.prediction_limiter)
    result = {"frames": args.frames, "iterations": args.iterations, "metric": cfg.metric, "prediction": cfg.motion_prediction(),
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


SCENES = {"one_hand": "09", "two_hands_object": "16"}


def throughput() -> dict:
    """This machine's single-thread throughput: float32 matmul GFLOP/s (512 x 512) and
    copy GB/s (32 MB read and written), medians of 20 runs."""
    import statistics
    a, b = torch.randn(512, 512), torch.randn(512, 512)
    x, y = torch.empty(8 << 20), torch.empty(8 << 20)

    def best(fn):
        fn()
        ts = []
        for _ in range(20):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return statistics.median(ts)

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gflops = 2 * 512 ** 3 / best(lambda: a @ b) / 1e9
        gbps = 2 * x.numel() * 4 / best(lambda: y.copy_(x)) / 1e9
    finally:
        torch.set_num_threads(old)
    return {"matmul_gflops": gflops, "copy_gbps": gbps}


def profile(args) -> dict:
    """``--profile``: the stage table of each scene (and with ``--fused`` the fused
    iteration's, in the same run)."""
    from torchhand.core.profiling import recording

    speed = throughput()
    cfg = TrackerConfig(metric="point-to-plane", max_iterations=args.profile_cap,
                        first_frame_iterations=args.iterations, prediction=args.prediction,
                        prediction_limiter=args.prediction_limiter)
    out = {"profile_cap": args.profile_cap, "prediction": cfg.motion_prediction(), **speed, "scenes": {}}
    variants = {"torch": cfg}
    if args.fused:
        variants["fused"] = replace(cfg, fused=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for key in [k for k in args.scenes.split(",") if k.strip()]:
            root = render(args.hia_root, SCENES[key], 0, args.frames, tmp / key)
            scene = out["scenes"][key] = {}
            for name, c in variants.items():
                run = scored_run(root, tmp / f"{key}_{name}", c, args.device)  # warm-up and accuracy
                with recording(synchronize=args.device.startswith("cuda")) as rec:
                    wall, secs = timed_track([root], tmp / f"{key}_{name}_p", c, args.device)
                scene[name] = {**run, **stage_table(rec, speed)}
                print_table(f"{key} ({name}, cap {args.profile_cap})", scene[name])
            alternate(scene, variants, root, tmp / f"{key}_again", args)
            t = scene["torch"]
            out[f"{key}_ms"], out[f"{key}_px"] = 1e3 * t["seconds_per_frame_after_first"], t["mean_px"]
            if args.hold_frames > 0:
                held = hold(args, key, cfg, tmp)
                scene["torch"]["held"] = held
                out[f"{key}_held_px"], out[f"{key}_held_worst_mm"] = held["mean_px"], held["worst_frame_mm"]
                out[f"{key}_held_ms"] = 1e3 * held["seconds_per_frame_after_first"]
            if "fused" in scene:
                f = scene["fused"]
                out[f"{key}_ms_fused"], out[f"{key}_px_fused"] = 1e3 * f["seconds_per_frame_after_first"], f["mean_px"]
                after = "seconds_per_frame_after_first"
                scene["fused_speedup_vs_torch"] = t[after] / f[after]
                scene["fused_lm_speedup_vs_torch"] = t["lm_ms_per_frame"] / f["lm_ms_per_frame"]
                scene["theta_max_diff_rad"], scene["theta_max_diff_mm"] = theta_difference(
                    tmp / f"{key}_torch", tmp / f"{key}_fused", root)
                if key == "one_hand":
                    out["fused_speedup_vs_torch"] = scene["fused_speedup_vs_torch"]
    return out


def hold(args, key: str, cfg: TrackerConfig, tmp: Path) -> dict:
    """``--hold-frames``: scene ``key`` tracked at ``cfg``'s cap over its first
    ``args.hold_frames`` frames and scored."""
    root = render(args.hia_root, SCENES[key], 0, args.hold_frames, tmp / f"{key}_hold")
    held = {"frames": args.hold_frames, **scored_run(root, tmp / f"{key}_hold_out", cfg, args.device)}
    print(f"{key} over {args.hold_frames} frames at cap {args.profile_cap}: {held['mean_px']:.2f} px, "
          f"worst frame {held['worst_frame_mm']:.1f} mm, {1e3 * held['seconds_per_frame_after_first']:.1f} ms/frame")
    return held


def alternate(scene: dict, variants: dict, root: Path, out: Path, args) -> None:
    """``--repeats`` more unprofiled runs of every variant, alternating (torch, fused,
    torch, ...), so that a change of the machine's load falls on both: each variant's
    ``seconds_per_frame_after_first`` becomes the median over its runs (the single runs
    in ``runs_after_first``)."""
    import statistics

    runs = {name: [scene[name]["seconds_per_frame_after_first"]] for name in variants}
    for _ in range(args.repeats):
        for name, c in variants.items():
            timed_track([root], out, c, args.device)
            log = json.loads(next(out.glob("*/track_log.json")).read_text())
            runs[name].append(sum(f["seconds"] for f in log["frames"][1:]) / max(len(log["frames"]) - 1, 1))
    for name in variants:
        scene[name]["runs_after_first"] = runs[name]
        scene[name]["seconds_per_frame_after_first"] = statistics.median(runs[name])


def theta_difference(a: Path, b: Path, root: Path) -> tuple:
    """The largest |theta| difference of two runs' outputs of the sequence ``root`` over
    all frames: (rotations and joint angles, rad; root translations, mm)."""
    import numpy as np

    from torchhand.model.scene import Scene

    (ta,), (tb,) = (list(Path(x).glob("*/theta.npy")) for x in (a, b))
    d = np.abs(np.load(ta).astype(np.float64) - np.load(tb).astype(np.float64))
    models = json.loads(SequenceLayout(root).info.read_text())["models"]
    names = Scene.from_names(models).dof_names
    trans = np.array([n.split("/")[-1] in ("root:tx", "root:ty", "root:tz") for n in names])
    return float(d[:, ~trans].max()), float(d[:, trans].max())


def stage_table(rec, speed: dict) -> dict:
    """Per stage path: ms per frame after frame 0, calls per frame, floor ms per frame."""
    frames, current = [], {}
    for path, s, f, b in rec.events:  # a frame's stages end before the frame does
        if not path.startswith("frame"):
            continue
        t = current.setdefault(path, [0, 0.0, 0.0, 0.0])
        t[0] += 1
        t[1] += s
        t[2] += f
        t[3] += b
        if path == "frame":
            frames.append(current)
            current = {}
    later = frames[1:] or frames
    n = len(later)
    iters = sum(fr.get("frame/iteration", [0])[0] for fr in later) / max(n, 1)
    rows = []
    for path in dict.fromkeys(p for fr in frames for p in fr):
        calls, secs, flops, nbytes = (sum(fr.get(path, [0, 0.0, 0.0, 0.0])[i] for fr in later) / n for i in range(4))
        floor = max(flops / (speed["matmul_gflops"] * 1e9), nbytes / (speed["copy_gbps"] * 1e9))
        rows.append({"stage": path[len("frame/"):] or "frame", "calls_per_frame": calls, "ms_per_frame": 1e3 * secs,
                     "ms_per_iteration": 1e3 * secs / max(iters, 1e-9), "mflop_per_frame": flops / 1e6,
                     "mb_per_frame": nbytes / 1e6, "floor_ms_per_frame": 1e3 * floor if flops or nbytes else None})
    lm = sum(r["ms_per_frame"] for r in rows if r["stage"] == "iteration/lm")
    return {"profiled_frames": n, "profiled_iterations_per_frame": iters, "lm_ms_per_frame": lm, "stages": rows}


def print_table(title: str, table: dict) -> None:
    print(f"\n{title}: {table['seconds_per_frame_after_first'] * 1e3:.1f} ms/frame after frame 0 (unprofiled), "
          f"{table['profiled_iterations_per_frame']:.2f} iterations/frame, {table['mean_px']:.2f} px")
    print(f"{'stage':<44} {'calls':>6} {'ms/frame':>9} {'ms/iter':>8} {'floor ms':>9}")
    for r in table["stages"]:
        floor = "" if r["floor_ms_per_frame"] is None else f"{r['floor_ms_per_frame']:.3f}"
        print(f"{r['stage']:<44} {r['calls_per_frame']:>6.1f} {r['ms_per_frame']:>9.2f} {r['ms_per_iteration']:>8.2f} "
              f"{floor:>9}")


def within_targets(run: dict) -> bool:
    return run["mean_px"] <= 3.0 and run["mean_mm"] <= 6.0 and run["worst_frame_mm"] <= 20.0


if __name__ == "__main__":
    main()
