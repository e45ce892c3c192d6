"""A synthetic rig of depth cameras against its camera 0 alone (docs/multicam.md).

    python eval/exp_depth_rig.py --hia-root ../shared/data/hands_in_action --json out/exp_depth_rig.json

For each of ``--sequences`` (``NN`` or ``NN@START``), ``--frames`` frames of the thesis
motion are rendered with the kinect noise model twice: by camera 0 alone (``torchhand
synth``'s single view) and by a ring of ``--views`` depth cameras around the scene
(:func:`torchhand.data.synth.with_camera_ring`; camera 0 keeps its place, so both share
the world frame and the ground truth). Each is tracked from the true first pose with the
CLI's default tracker settings (every view's depth in the energy for the rig) and
scored against the truth: mean and worst-frame joint error (mm), and camera 0's px.
The rig's views are cut to the hands (``TrackerConfig.crop_views``) and its depth terms
pair two views' worth of model vertices and pixels spread over them
(``TrackerConfig.rig_budget``), the defaults; ``--whole-views`` tracks it once more with
every view whole (its whole image and every term's whole caps; ``whole_views_*`` keys).
``time_ratio`` is the rig's seconds per frame after frame 0 over camera 0's, measured
side by side in one run; ``mm_ratio`` its mean error over camera 0's (at most 1 and at
most 2 are the targets).

``--profile``: each sequence's camera 0 and rig tracked once more under the project's
stage recorder (:mod:`torchhand.core.profiling`, as ``eval/bench_track.py --profile``):
the ms per frame of every stage after frame 0, side by side (``profile`` keys; the
profiled run is slower than the unprofiled ones, so compare its stages with each other).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, set_threads, write_json  # noqa: E402
from bench_track import print_table, scored_run, stage_table, throughput, timed_track  # noqa: E402

from torchhand.data.synth import thesis_motion, with_camera_ring, write_synthetic_sequence  # noqa: E402
from torchhand.tracking.tracker import TrackerConfig  # noqa: E402


def _window(spec: str) -> tuple:
    seq, _, start = spec.partition("@")
    return seq, int(start or 0)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--sequences", default="10,03", help="comma-separated NN or NN@START")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--profile", action="store_true", help="also the stages of camera 0 and of the rig, side by side")
    ap.add_argument("--whole-views", action="store_true",
                    help="also track the rig with every view whole (its whole image, every term's whole caps), "
                         "side by side")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    cfg = TrackerConfig()
    result = {"machine": machine(), "views": args.views, "frames": args.frames, "sequences": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for spec in args.sequences.split(","):
            seq, start = _window(spec)
            fr = thesis_motion(args.hia_root, seq, slice(start, start + args.frames), dtype=torch.float32)
            fr.name = f"hia_{seq}_{start}"
            single = write_synthetic_sequence(fr, tmp / "single" / fr.name, noise="kinect", seed=start, rgb=False,
                                              progress=False)
            ring = with_camera_ring(replace(fr, name=f"{fr.name}_rig{args.views}"), args.views)
            rig = write_synthetic_sequence(ring, tmp / "rig" / ring.name, noise="kinect", seed=start,
                                           colour="shaded", depth=True, progress=False)
            row = {"camera_0": scored_run(single, tmp / "out_single", cfg),
                   f"rig_{args.views}": scored_run(rig, tmp / "out_rig", cfg)}
            a, b = row["camera_0"], row[f"rig_{args.views}"]
            row["time_ratio"] = b["seconds_per_frame_after_first"] / a["seconds_per_frame_after_first"]
            row["mm_ratio"] = b["mean_mm"] / a["mean_mm"]
            if args.whole_views:  # the rig again with whole images, side by side
                c = row[f"rig_{args.views}_whole_views"] = scored_run(rig, tmp / "out_whole",
                                                                      replace(cfg, crop_views=False, rig_budget=None))
                row["whole_views_time_ratio"] = c["seconds_per_frame_after_first"] / a["seconds_per_frame_after_first"]
                row["whole_views_mm_ratio"] = c["mean_mm"] / a["mean_mm"]
            if args.profile:
                row["profile"] = _profile({"camera_0": (single, a), f"rig_{args.views}": (rig, b)}, cfg, tmp)
            result["sequences"][spec] = row
            print(f"{spec}: camera 0 {a['mean_mm']:.2f} mm, {1000 * a['seconds_per_frame_after_first']:.0f} ms; "
                  f"{args.views} views {b['mean_mm']:.2f} mm, {1000 * b['seconds_per_frame_after_first']:.0f} ms",
                  flush=True)
    write_json(args.json, result)


def _profile(runs: dict, cfg: TrackerConfig, tmp: Path) -> dict:
    """``--profile``: name -> its stage table (``stage_table``), each run's sequence
    tracked once under the stage recorder."""
    from torchhand.core.profiling import recording

    speed = throughput()
    out = {}
    for name, (root, scored) in runs.items():
        with recording() as rec:
            timed_track([root], tmp / f"profile_{name}", cfg)
        out[name] = {**scored, **stage_table(rec, speed)}
        print_table(name, out[name])
    return out


if __name__ == "__main__":
    main()
