"""Synthesis speed: 640x480 depth of two hands and an object, written as a sequence.

    python eval/bench_synth.py --json out/bench_synth.json [--frames 60] [--noise kinect]

Times ``write_synthetic_sequence`` on the shipped demo motion (two hands and the ball):
posing, rendering, the noise model and PNG writing, depth only and depth + RGB, for each
of ``--backends``. Writes {"synth_fps": depth-only frames/s of the default backend,
"backends": {name: {"depth_fps", "depth_rgb_fps"}}, "synth_speedup_vs_open3d", ...}.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from _common import machine, set_threads, write_json
from torchhand.data.synth import demo_motion, write_synthetic_sequence


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--noise", default="kinect")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--backends", default="warp,open3d", help="comma-separated render backends")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    frames = demo_motion(slice(0, args.frames))
    result = {"frames": len(frames.theta), "noise": args.noise, "models": frames.scene.names, "backends": {},
              **machine()}
    with tempfile.TemporaryDirectory() as tmp:
        write_synthetic_sequence(demo_motion(slice(0, 2)), Path(tmp) / "warm", noise=args.noise, progress=False)
        for backend in args.backends.split(","):
            r = result["backends"][backend] = {}
            for key, rgb in (("depth_fps", False), ("depth_rgb_fps", True)):
                t0 = time.perf_counter()
                write_synthetic_sequence(frames, Path(tmp) / f"{backend}_{key}", noise=args.noise, rgb=rgb,
                                         progress=False, backend=backend)
                r[key] = len(frames.theta) / (time.perf_counter() - t0)
    first = args.backends.split(",")[0]
    result["synth_fps"] = result["backends"][first]["depth_fps"]
    if "open3d" in result["backends"] and "warp" in result["backends"]:
        result["synth_speedup_vs_open3d"] = result["backends"]["warp"]["depth_fps"] / result["backends"]["open3d"]["depth_fps"]
    write_json(args.json, result)


if __name__ == "__main__":
    main()
