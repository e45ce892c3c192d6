"""Round trip of the thesis motions through torchhand's pose parameters.

For every sequence under ``--hia-root`` that has MOTION files, every model of the
sequence is converted MOTION -> theta (``torchhand.model.motion.motion_to_theta``) and
posed by theta -> forward kinematics -> LBS; the vertices are compared with the
original viewer's posing ``sum_b w_b Mk_b M0_b^-1 v`` of the same frames.

    python eval/check_hia_roundtrip.py --hia-root ../shared/data/hands_in_action --json out/roundtrip.json

Writes {"sequences": [...], "frames": N, "median_mm": x, "max_mm": y, "per_sequence": {...}}.
Models are read from the sequence's own files (not from models/), so sequences with
other meshes or limits are checked as they are. Each sequence's entry also says how far
its theta leaves the models' joint limits (``limits``: the frames with any joint
outside, the joints ever outside, the largest excess in radians and its joint), which
is why the tracker's box grows to hold each sequence's first pose (docs/results.md
"Joint limits").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchhand.io import assets_from_thesis, read_thesis_model, sequence_models
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.motion import motion_tensor, motion_to_theta, pose_like_viewer


def check_sequence(hia_root: Path, seq: str, chunk: int = 64):
    """Per-vertex errors (mm) of all frames of all models of one sequence, its frame
    count and its theta's excess over the joint limits (a dict)."""
    names, bounds = sequence_models(hia_root, seq)
    errors, outside = [], []  # outside: per model, (frames, its DoF) excess over its limits
    dof_names: list = []
    frames = None
    for name in names:
        files = read_thesis_model(hia_root / "Models" / seq, name)
        if files.motion is None:
            return None, 0, None
        model = ArticulatedModel(assets_from_thesis(files), dtype=torch.float64)
        M_all = motion_tensor(model, files.motion)
        # Video frame k uses MOTION row k + MotionnOffset (data README).
        rows = torch.arange(bounds.total_aligned) + bounds.motion_offset
        rows = rows[rows < len(M_all)]
        frames = len(rows)
        order = [files.skin.bone_names.index(b) for b in model.bone_names]
        W = torch.as_tensor(files.skin.weights[:, order])
        excess = []
        for s in range(0, len(rows), chunk):
            M = M_all[rows[s : s + chunk]]
            theta = motion_to_theta(model, M)
            with torch.no_grad():
                ours = model(theta).vertices
                ref = pose_like_viewer(model.vertices_rest, W, M, M_all[0])
            errors.append((ours - ref).norm(dim=-1).flatten().float())
            excess.append(model.limit_violation(theta).abs())
        dof_names += [f"{name}/{d}" for d in model.dof_names]
        outside.append(torch.cat(excess))
    over = torch.cat(outside, 1)  # (frames, DoF of every model)
    worst = over.max(0).values
    limits = {"frames_outside": int((over > 1e-6).any(1).sum()), "dofs_outside": int((worst > 1e-6).sum()),
              "max_rad": float(worst.max()), "worst_dof": dof_names[int(worst.argmax())]}
    return torch.cat(errors), frames, limits


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--sequences", default=None, help="comma-separated sequence ids, e.g. 01,16 (default: all)")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    cfg = args.hia_root / "Configs"
    if not cfg.is_dir():
        ap.error(f"{cfg} not found: --hia-root must contain Configs/ and Models/")
    seqs = args.sequences.split(",") if args.sequences else sorted(p.name for p in cfg.iterdir() if p.is_dir())
    used, per_seq, all_err, frames = [], {}, [], 0
    for seq in tqdm(seqs, desc="sequences", unit="seq"):
        if not (cfg / seq).is_dir():
            ap.error(f"sequence {seq} not found under {cfg}")
        err, n, limits = check_sequence(args.hia_root, seq)
        if err is None:
            tqdm.write(f"sequence {seq}: no MOTION files, skipped")
            continue
        used.append(seq)
        frames += n
        all_err.append(err)
        per_seq[seq] = {"frames": n, "median_mm": float(err.median()), "max_mm": float(err.max()), "limits": limits}
    if not all_err:
        print("no sequence with MOTION files found", file=sys.stderr)
        return 1
    err = torch.cat(all_err)
    # torch.median/quantile on >16M elements: use numpy for the global median.
    result = {"sequences": used, "frames": frames, "median_mm": float(np.median(err.numpy())),
              "max_mm": float(err.max()), "per_sequence": per_seq}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(json.dumps({k: result[k] for k in ("sequences", "frames", "median_mm", "max_mm")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
