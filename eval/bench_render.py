"""Rendering speed of the backends side by side: 640x480, two thesis hands plus the ball
(demo motion poses), depth, ids, normals and silhouette edges.

    python eval/bench_render.py --json out/bench_render.json [--frames 30] [--device cpu]

Each backend renders the same frames through one :class:`~torchhand.geometry.render.Renderer`
(the BVH of ``warp-raycast`` refits from frame to frame; open3d builds one per frame,
the meshes deform). Writes per backend ``ms_per_frame`` and ``fps``, their agreement with
open3d on the first three frames (largest depth difference in mm, share of pixels with
the same face), and
``render_speedup_vs_open3d`` (open3d time / Warp rasterisation time).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from _common import demo_scene, machine, set_threads, write_json
from torchhand.geometry.raycast import BACKENDS
from torchhand.geometry.render import Renderer


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--device", default="cpu", help="torch device of the Warp backends (open3d renders on the CPU)")
    ap.add_argument("--backends", default=",".join(BACKENDS), help="comma-separated backends")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    names, theta, scene, cam = demo_scene()
    with torch.no_grad():
        verts = scene(theta[: args.frames]).vertices
    result = {"frames": len(verts), "triangles": int(scene.faces.shape[0]), "image": [640, 480], "models": names,
              "device": args.device, "backends": {}, **machine()}
    if args.device.startswith("cuda"):
        result["cuda_device"] = torch.cuda.get_device_name(torch.device(args.device))
    outputs = {}
    for backend in args.backends.split(","):
        dev = "cpu" if backend == "open3d" else args.device
        r = Renderer(scene.faces.to(dev), scene.face_model_id.to(dev), scene.face_bone_id.to(dev), backend=backend)
        camera, V = cam.to(dev), verts.to(dev)
        r(V[:1], camera)  # warm-up: kernels, caches
        _sync(dev)
        t0 = time.perf_counter()
        for k in range(len(V)):
            r(V[k : k + 1], camera)  # results dropped: allocation stays as in use
        _sync(dev)
        dt = (time.perf_counter() - t0) / len(V)
        outputs[backend] = [r(V[k : k + 1], camera) for k in range(min(3, len(V)))]  # for the agreement
        result["backends"][backend] = {"ms_per_frame": 1000 * dt, "fps": 1.0 / dt}
    if "open3d" in outputs:
        for backend, outs in outputs.items():
            ref = outputs["open3d"]
            depth = max(float((a.depth.cpu() - b.depth).abs().max()) for a, b in zip(outs, ref))
            same = sum(int((a.face_id.cpu() == b.face_id).sum()) for a, b in zip(outs, ref))
            result["backends"][backend].update(max_depth_diff_mm=depth,
                                               same_face_fraction=same / sum(b.face_id.numel() for b in ref))
        if "warp" in outputs:
            result["render_speedup_vs_open3d"] = (result["backends"]["open3d"]["ms_per_frame"]
                                                  / result["backends"]["warp"]["ms_per_frame"])
    write_json(args.json, result)


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


if __name__ == "__main__":
    main()
