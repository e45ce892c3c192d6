"""In-hand scanning experiment (thesis Ch. 5, Table 5.1's question on renders with truth).

For each object and noise model: render an in-hand scan (``torchhand synth
--scan-object``), scan it with the pipeline (``torchhand scan``) and with the
KinectFusion-style baseline (``--baseline``), and score both against the true mesh and
motion (:func:`torchhand.scoring.surfaces.score_scan`): symmetric mean surface distance
and Hausdorff 95 % after rigid alignment, watertightness, the trajectory's rotation and
translation errors, seconds per frame.

Objects: the shipped ball, cube and pipe, and two asymmetric prisms made here (an
L-block and a T-block). With ``--hia-root``, the cube scanned with kinect noise then
replaces the shipped cube in tracking thesis sequence 20 (one hand and the cube,
rendered with kinect noise): the hand's and the cube's errors with either model.
Usage::

    python eval/exp_scan.py --json out/scan.json [--objects cube,lblock] [--noise kinect] [--frames 180]
        [--hia-root ../shared/data/hands_in_action]
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


def scanned_pose(theta_object: np.ndarray, object_root: np.ndarray, alignment: np.ndarray) -> np.ndarray:
    """theta (6,) of a scanned model that puts its surface where the shipped model at
    ``theta_object`` puts its own: ``alignment`` (4, 4) maps the scanned model's
    coordinates to the shipped mesh's; the shipped model turns about its root joint
    ``object_root`` (3,)."""
    import torch

    from torchhand.model.kinematics import so3_exp, so3_log

    R = so3_exp(torch.as_tensor(theta_object[None, 3:6]))[0].numpy()
    t = theta_object[:3]
    A_R, A_t = alignment[:3, :3], alignment[:3, 3]
    R_s = R @ A_R
    t_s = R @ (A_t - object_root) + object_root + t
    return np.concatenate([t_s, so3_log(torch.as_tensor(R_s)[None])[0].numpy()])


def track_with_scan(hia_root: Path, work: Path, scan_dir: Path, alignment: np.ndarray, sequence: str = "20") -> dict:
    """Track thesis ``sequence`` (hand + cube) with the shipped cube and with the scan."""
    import dataclasses
    import shutil

    from torchhand.app.runner import track_sequences
    from torchhand.data.layout import (OutputLayout, SequenceLayout, read_init_pose, read_sequence_info,
                                       write_sequence_info)
    from torchhand.data.synth import thesis_motion, write_synthetic_sequence
    from torchhand.io.assets import find_model, load_assets
    from torchhand.scoring.sequences import evaluate_sequence

    seq = write_synthetic_sequence(thesis_motion(hia_root, sequence), work / f"hia_{sequence}", force=True,
                                   progress=False)
    info = read_sequence_info(seq)
    if info.models != ["hand_right", "cube"]:
        raise ValueError(f"sequence {sequence}: expected hand_right and cube, got {info.models}")
    theta = read_init_pose(seq)
    cube = load_assets(find_model("cube"))
    k = 37  # the hand's DoF come first
    scanned = work / f"hia_{sequence}_scanned"
    if scanned.exists():
        shutil.rmtree(scanned)
    shutil.copytree(seq, scanned, ignore=shutil.ignore_patterns(SequenceLayout(seq).gt.root.name))
    theta_s = np.concatenate([theta[:k], scanned_pose(theta[k:], cube.rest_transforms[0, :3, 3], alignment)])
    write_sequence_info(scanned, dataclasses.replace(info, models=["hand_right", str(scan_dir / "model.npz")]),
                        init_theta=theta_s)
    out = {}
    for name, root in (("shipped", seq), ("scanned", scanned)):
        res = track_sequences([root], work / f"track_{sequence}_{name}", force=True, progress=False,
                              names=[name])[0]
        pred = np.load(OutputLayout(work / f"track_{sequence}_{name}" / name).keypoints_3d)
        gt = np.load(SequenceLayout(seq).gt.keypoints_3d)  # the hand's 21 keypoints (the cubes have none)
        e = np.linalg.norm(pred - gt, axis=-1).mean(-1)[:, 0]
        out[name] = {"hand_mean_mm": float(e.mean()), "hand_median_mm": float(np.median(e)),
                     "hand_worst_frame_mm": float(e.max()), "seconds_per_frame": res["seconds_per_frame"],
                     "mean_iou": res["mean_iou"]}
        if name == "shipped":
            ev = evaluate_sequence(work / f"track_{sequence}_{name}" / name, SequenceLayout(seq).gt,
                                   with_penetration=False)
            out[name]["cube_mean_mm"] = ev["models"]["cube"]["mean_mm"]
        print(sequence, name, out[name], flush=True)
    out["hand_error_ratio"] = out["scanned"]["hand_mean_mm"] / out["shipped"]["hand_mean_mm"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--objects", default="ball,cube,pipe,lblock,tblock")
    ap.add_argument("--noise", default="none,kinect")
    ap.add_argument("--frames", type=int, default=None, help="frames per scan (default: two turns, 180)")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: out/exp_scan)")
    ap.add_argument("--hia-root", type=Path, default=None, help="thesis data: track sequence 20 with the scanned cube")
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
    result = {"rows": rows}
    if args.hia_root is not None:
        cube = next((r for r in rows if r["object"] == "cube" and r["noise"] == "kinect" and "alignment" in r["ours"]),
                    None)
        if cube is None:
            raise SystemExit("--hia-root needs the cube scanned with kinect noise (--objects cube --noise kinect)")
        result["track_with_scan"] = track_with_scan(args.hia_root, work, work / "scan_cube_kinect_ours",
                                                    np.asarray(cube["ours"]["alignment"]))
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
