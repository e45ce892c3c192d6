"""Rigged models of articulated objects (thesis Ch. 6): Table 6.2's setting and objects
with joints at known places.

    python eval/exp_rig.py --hia-root ../shared/data/hands_in_action --json out/exp_rig.json

- ``pipe``: thesis sequence 17 ("Bending a pipe", two hands), the first ``--frames``
  frames rendered noise-free; ``rope``: the same motion with the rope in the pipe's
  place (``eval/exp_tracking.py``'s :func:`rope_from_pipe_sequence`). Each is rigged with
  ``torchhand rig --hands hand_right,hand_left`` from the shipped template over the
  thesis' grid (gamma_def 0.005, 0.05 x lambda_thr 0.7, 0.98; and without d^n at 0.005,
  0.7), then tracked with the learned rig; the average vertex error against the true
  motion, per frame and averaged (Eq. 6.13's closest-vertex distance, and the distance
  of corresponding vertices), of the deformable tracking and of the articulated tracking.
  ``--grid defaults`` runs the defaults only.
- ``chain2``, ``chain3``: tubes of two and three links (:mod:`torchhand.data.chains`)
  bending in front of the camera, no hands, noise-free; ``chain2_kinect``: links of 80
  and 140 mm, radius 12 mm, another motion, with Kinect noise. The parts found, the joint position error
  (each true joint to the nearest learned one), the tracking error with the learned rig
  and, in the same run, with the true rig.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from torchhand.app.rig import rig_folder  # noqa: E402
from torchhand.app.runner import TrackOptions, track_sequences  # noqa: E402
from torchhand.data.layout import OutputLayout, SequenceLayout, read_poses, read_sequence_info  # noqa: E402
from torchhand.data.synth import thesis_motion, write_synthetic_sequence  # noqa: E402
from torchhand.io.assets import save_assets  # noqa: E402
from torchhand.model.scene import Scene  # noqa: E402
from torchhand.reconstruction.deformable import DeformConfig  # noqa: E402
from torchhand.scoring.surfaces import vertex_errors  # noqa: E402

#: the generated objects: name, link lengths (mm), joint axes, radius (mm), noise, motion seed
CHAINS = [("chain2", (120.0, 120.0), ("z",), 15.0, "none", 1),
          ("chain3", (100.0, 90.0, 90.0), ("z", "y"), 15.0, "none", 1),
          ("chain2_kinect", (80.0, 140.0), ("z",), 12.0, "kinect", 3)]
GRID = [(0.005, 0.7, True), (0.005, 0.98, True), (0.05, 0.7, True), (0.05, 0.98, True), (0.005, 0.7, False)]


def _truth(seq: Path, model: str, frames: int) -> tuple:
    """(world, camera-0) true vertices (N, V, 3) of ``model`` in the sequence."""
    info = read_sequence_info(seq)
    scene = Scene.from_names(info.models, dtype=torch.float64)
    th = torch.as_tensor(read_poses(SequenceLayout(seq).gt).theta[:frames])
    with torch.no_grad():
        v = scene(th).vertices[:, scene.vertex_slices[model]]
        cam = info.cameras[0].to(dtype=torch.float64)
        return v.numpy(), cam.to_camera(v).numpy()


def _score(out: Path, log: dict, world: np.ndarray, camera: np.ndarray) -> dict:
    dv = np.load(out / "deformable" / "vertices.npy")
    d = vertex_errors(dv, world[:len(dv)])
    row = {"parts": log["parts"], "clusters": log["clusters"], "joint_dofs": log["joint_dofs"], "eigenvalues": log["eigenvalues"][:8],
           "deformable_mm": d["mean_closest_mm"], "deformable_same_order_mm": d["mean_same_order_mm"],
           "seconds": log["seconds"]}
    tv = OutputLayout(out / "track").vertices(log['name'])
    if tv.is_file():
        t = vertex_errors(np.load(tv), camera[:len(dv)])
        row.update(tracked_mm=t["mean_closest_mm"], tracked_same_order_mm=t["mean_same_order_mm"],
                   tracked_worst_frame_mm=float(t["closest_mm"].max()),
                   tracked_per_frame_mm=t["closest_mm"].round(3).tolist())
    return row


def table_62(args, name: str, seq: Path, template: str) -> list:
    world, camera = _truth(seq, template, args.frames)
    rows = []
    for gamma, lam, normals in (GRID if args.grid == "thesis" else GRID[:1]):
        tag = f"{name}_g{gamma:g}_l{lam:g}{'' if normals else '_nodn'}"
        out = args.work / tag
        t0 = time.perf_counter()
        log = rig_folder(seq, template, out, hands=["hand_right", "hand_left"], name=f"rig_{name}",
                         deform=DeformConfig(gamma_def=gamma), lambda_thr=lam, use_normals=normals,
                         frames=args.frames, force=True, progress=False)
        row = {"object": name, "gamma_def": gamma, "lambda_thr": lam, "d_n": normals, **_score(out, log, world, camera),
               "wall_s": time.perf_counter() - t0}
        print(f"{tag}: {row['parts']} parts, deformable {row['deformable_mm']:.2f} mm, tracked "
              f"{row.get('tracked_mm', float('nan')):.2f} mm, {row['wall_s']:.0f} s", flush=True)
        rows.append(row)
    return rows


def chains(args) -> list:
    from torchhand.data.chains import chain_joints, chain_motion, chain_object

    models = args.work / "models"
    models.mkdir(parents=True, exist_ok=True)
    os.environ["TORCHHAND_MODELS"] = str(models)
    rows = []
    for name, lengths, axes, radius, noise, seed in CHAINS:
        assets = chain_object(lengths, axes, radius=radius, name=name)
        save_assets(assets, models / f"{name}.npz", overwrite=True)
        seq = write_synthetic_sequence(chain_motion(assets, args.frames, seed=seed), args.work / f"{name}_seq",
                                       noise=noise, rgb=False, force=True, progress=False)
        world, camera = _truth(seq, name, args.frames)
        t0 = time.perf_counter()
        out = args.work / f"{name}_rig"
        log = rig_folder(seq, name, out, name=f"rig_{name}", force=True, progress=False)
        row = {"object": name, "noise": noise, "true_parts": len(lengths), **_score(out, log, world, camera),
               "wall_s": time.perf_counter() - t0}
        learned = np.asarray(log["joints_mm"]).reshape(-1, 3)
        true = chain_joints(assets)
        row["joint_error_mm"] = (np.linalg.norm(true[:, None] - learned[None], axis=-1).min(1).round(3).tolist()
                                 if len(learned) else None)
        # the same sequence tracked with the true rig, in this run
        truth_out = args.work / f"{name}_true_track"
        track_sequences([seq], truth_out, TrackOptions(reinit_iou=0.0, write_vertices=True), names=["track"],
                        force=True, progress=False)
        t = vertex_errors(np.load(OutputLayout(truth_out / "track").vertices(name)), camera)
        row.update(true_rig_tracked_mm=t["mean_closest_mm"], true_rig_same_order_mm=t["mean_same_order_mm"])
        print(f"{name}: {row['parts']} parts (true {len(lengths)}), joints off by {row['joint_error_mm']} mm, "
              f"tracked {row.get('tracked_mm', float('nan')):.2f} mm (true rig {row['true_rig_tracked_mm']:.2f} mm), "
              f"{row['wall_s']:.0f} s", flush=True)
        rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hia-root", type=Path, help="Hands-in-Action data (for the pipe and rope rows)")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--work", type=Path, default=Path("out/exp_rig"))
    p.add_argument("--only", default="pipe,rope,chains", help="comma-separated: pipe, rope, chains")
    p.add_argument("--grid", choices=["thesis", "defaults"], default="thesis",
                   help="the pipe and the rope over the thesis' grid, or at the defaults only")
    p.add_argument("--json", type=Path, required=True)
    args = p.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    only = args.only.split(",")
    result = {"frames": args.frames, "rows": []}
    if "pipe" in only or "rope" in only:
        if args.hia_root is None:
            p.error("--hia-root is needed for the pipe and rope rows")
    if "chains" in only:
        result["rows"] += chains(args)
        _dump(args, result)
    if "pipe" in only:
        seq = args.work / "pipe17_seq"
        if not SequenceLayout(seq).gt.meta.is_file():
            write_synthetic_sequence(thesis_motion(args.hia_root, "17", slice(0, args.frames)), seq, noise="none",
                                     rgb=False, force=True, progress=False)
        result["rows"] += table_62(args, "pipe", seq, "pipe")
        _dump(args, result)
    if "rope" in only:
        from exp_tracking import rope_from_pipe_sequence

        seq = rope_from_pipe_sequence(args.hia_root, args.frames, args.work, "none")
        result["rows"] += table_62(args, "rope", seq, "rope")
    _dump(args, result)
    print(markdown(result))
    return 0


def markdown(result: dict) -> str:
    """The tables of docs/results.md from the JSON of a run."""
    lines = ["| object | gamma_def | lambda_thr | d^n | parts | deformable (mm) | tracked with the rig (mm) "
             "| worst frame (mm) | s per 200 frames |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if "gamma_def" in r:
            dn = "yes" if r["d_n"] else "no"
            lines.append(f"| {r['object']} | {r['gamma_def']:g} | {r['lambda_thr']:g} | {dn} | "
                         f"{r['parts']} | {r['deformable_mm']:.2f} | {r.get('tracked_mm', float('nan')):.2f} | "
                         f"{r.get('tracked_worst_frame_mm', float('nan')):.1f} | {r['seconds']['total']:.0f} |")
    lines += ["", "| object | parts (true) | joint error (mm) | deformable (mm) | tracked, learned rig (mm) | "
              "tracked, true rig (mm) | s |", "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if "true_parts" in r:
            joints = ", ".join(f"{e:.1f}" for e in r["joint_error_mm"] or [])
            lines.append(f"| {r['object']} | {r['parts']} ({r['true_parts']}) | {joints} | {r['deformable_mm']:.2f} | "
                         f"{r.get('tracked_mm', float('nan')):.2f} | {r['true_rig_tracked_mm']:.2f} | "
                         f"{r['seconds']['total']:.0f} |")
    return "\n".join(lines)


def _dump(args, result: dict) -> None:
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    sys.exit(main())
