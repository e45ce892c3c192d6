"""In-hand scanning experiment (thesis Ch. 5, Table 5.1's question on renders with truth).

For each object and noise model: render an in-hand scan (``torchhand synth
--scan-object``), scan it with the pipeline (``torchhand scan``) and with the
KinectFusion-style baseline (``--baseline``), and score both against the true mesh and
motion (:func:`torchhand.scoring.surfaces.score_scan`): symmetric mean surface distance
and Hausdorff 95 % after rigid alignment, watertightness, the trajectory's rotation and
translation errors, seconds per frame.

Objects: the shipped ball, cube and pipe, and two asymmetric prisms made here (an
L-block and a T-block). Usage::

    python eval/exp_scan.py --json out/scan.json [--objects cube,lblock] [--noise kinect] [--frames 180]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np




def prism(polygon, height: float, centre):
    """A closed prism over a 2D polygon (counter-clockwise, star-shaped around
    ``centre``): (V, 3) vertices, (F, 3) faces, outward."""
    P = np.asarray(polygon, np.float64)
    n = len(P)
    c = np.asarray(centre, np.float64)
    verts = np.concatenate([np.c_[P, np.zeros(n)], np.c_[P, np.full(n, height)], [[*c, 0.0], [*c, height]]])
    b, t = 2 * n, 2 * n + 1
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[b, j, i], [t, n + i, n + j], [i, j, n + j], [i, n + j, n + i]]
    v = verts - verts.mean(0)
    return v, np.array(faces, np.int64)


def make_objects(folder: Path) -> dict:
    """Mesh files of the objects (the shipped ones' meshes and the generated prisms)."""
    from torchhand.io.assets import find_model, load_assets
    from torchhand.io.mesh_files import write_mesh

    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name in ("ball", "cube", "pipe"):
        a = load_assets(find_model(name))
        paths[name] = write_mesh(folder / f"{name}.ply", a.vertices, a.faces)
    L = [(0, 0), (60, 0), (60, 25), (25, 25), (25, 70), (0, 70)]
    paths["lblock"] = write_mesh(folder / "lblock.ply", *prism(L, 30.0, (12, 12)))
    T = [(0, 0), (60, 0), (60, 20), (40, 20), (40, 70), (20, 70), (20, 20), (0, 20)]
    paths["tblock"] = write_mesh(folder / "tblock.ply", *prism(T, 30.0, (30, 10)))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--objects", default="ball,cube,pipe,lblock,tblock")
    ap.add_argument("--noise", default="none,kinect")
    ap.add_argument("--frames", type=int, default=None, help="frames per scan (default: two turns, 180)")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: out/exp_scan)")
    args = ap.parse_args(argv)
    from torchhand.app.scan import scan_folder
    from torchhand.data.scanning import write_scan_sequence
    from torchhand.scoring.surfaces import score_scan

    work = args.work or Path("out") / "exp_scan"
    paths = make_objects(work / "meshes")
    rows = []
    for obj in args.objects.split(","):
        for noise in args.noise.split(","):
            seq = write_scan_sequence(paths[obj], work / f"seq_{obj}_{noise}", frames=args.frames, noise=noise,
                                      force=True, progress=False)
            row = {"object": obj, "noise": noise}
            for method, baseline in (("ours", False), ("kinectfusion", True)):
                t0 = time.perf_counter()
                try:
                    log = scan_folder(seq, work / f"scan_{obj}_{noise}_{method}", force=True, baseline=baseline,
                                      progress=False)
                    score = score_scan(work / f"scan_{obj}_{noise}_{method}", seq)
                    score["seconds_per_frame"] = log["seconds"]["per_frame"]
                    score["faces"] = log["faces"]
                except Exception as err:  # a failed scan is a row, not the end of the experiment
                    score = {"error": str(err), "seconds": time.perf_counter() - t0}
                row[method] = score
                print(obj, noise, method, {k: v for k, v in score.items() if k != "trajectory"}, flush=True)
            if "mean_mm" in row["ours"] and "mean_mm" in row["kinectfusion"]:
                row["baseline_over_ours"] = row["kinectfusion"]["mean_mm"] / row["ours"]["mean_mm"]
            rows.append(row)
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
