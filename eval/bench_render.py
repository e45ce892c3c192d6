"""Depth rendering speed: 640x480, two thesis hands plus the ball (demo motion poses).

    python eval/bench_render.py --json out/bench_render.json [--frames 30]

Writes {"fps": f, "ms_per_frame": t, "triangles": n, ...}. One open3d RaycastingScene is
built per frame (the meshes deform), and only the pixels inside the projected bounding
box of the scene are cast.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from _common import demo_scene, machine, set_threads, write_json
from torchhand.geometry.render import render


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    names, theta, scene, cam = demo_scene()
    with torch.no_grad():
        verts = scene(theta[: args.frames]).vertices
    render(verts[:1], scene.faces, cam, scene.face_model_id, scene.face_bone_id)  # warm-up (ray cache)
    t0 = time.perf_counter()
    for k in range(len(verts)):
        render(verts[k : k + 1], scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    dt = (time.perf_counter() - t0) / len(verts)
    write_json(args.json, {"fps": 1.0 / dt, "ms_per_frame": 1000 * dt, "frames": len(verts),
                           "triangles": int(scene.faces.shape[0]), "image": [640, 480], "models": names, **machine()})


if __name__ == "__main__":
    main()
