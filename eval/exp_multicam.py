"""Ballan et al. 2012, Table 1: the multi-camera colour tracker with each visual feature
added in turn, on synthetic sequences with the paper's noise.

    python eval/exp_multicam.py --hia-root ../shared/data/hands_in_action --json out/exp_multicam.json

The paper's two synthetic sequences were "fingers crossing and folding" and "holding
and passing a ball"; their analogues here are windows of the shared thesis motions 03
(two hands, fingers interacting) and 16 (two hands and a ball), ``--frames`` frames
each, from ``--start`` or from the frame a sequence names as ``NN@START``. The default
window of 03 starts at frame 44, where its fingers cross (the hands are in contact from
about frame 44 to 132; over frames 0-40 they only approach, 13-40 mm apart, and
collisions have nothing to do); that of 16 at frame 0, the ball held and passed. Each
is rendered by ``torchhand synth``'s machinery with ``--views``
cameras around the scene (:func:`torchhand.data.synth.with_camera_ring`) at
``--image-scale`` times 640x480 (default 2: 1280x960 with f = 1050 px, the same field
of view; the paper's cameras recorded FullHD, and the pixel amounts of its noise are
those images'), shaded colour with nails and textured backgrounds, and the noise
protocol of the paper's Sec. 5
(``--protocol ballan``: 100 circles per image, salient detections deleted at 30 %,
outliers within 200 px, 5 px jitter). Each row is tracked by ``torchhand track``'s
runner from the first frame's true pose, with the energies E (edges), E+C (collisions),
E+C+O (optical flow) and E+C+O+S (salient points: the nails, the protocol's simulated
detections), all by the library's Levenberg-Marquardt ("LO"); ``LO+ECOS-net`` is E+C+O+S
with the nails found by the shipped colour detector in the noisy images instead
(``track --nails detector``); the HOPE rows run the particle swarm over the same energy
(``--hope 64,128``; 40 generations).

Columns, as in the paper: the joint position error (the 21 joints of each hand against
the truth, mean, std and max over joints and frames, mm) and the bone orientation error
(the angle between each tracked bone of the hand skeletons and the true one, degrees).
``s/frame`` is a row's wall time (tracking and writing its outputs) over its frames.
The JSON is written after each row (``"complete": false`` until the last), so a long
run keeps the rows it finished.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchhand.app.drawing import HAND_SKELETON
from torchhand.app.cli import limit_slack_arg
from torchhand.app.runner import TrackOptions, track_sequences
from torchhand.data.layout import SequenceLayout, read_poses
from torchhand.data.synth import thesis_motion, with_camera_ring, write_synthetic_sequence
from torchhand.tracking.tracker import TrackerConfig

#: (row label, --energy, --nails): the paper's rows with the protocol's simulated
#: detections, and one with the shipped colour nail detector instead
ROWS = [("LO+E", "E", "auto"), ("LO+EC", "E+C", "auto"), ("LO+ECO", "E+C+O", "auto"), ("LO+ECOS", "E+C+O+S", "auto"),
        ("LO+ECOS-net", "E+C+O+S", "detector")]
#: the sequences and the first frame of each one's window (``NN@START``)
SEQUENCES = ("03@44", "16@0")


def parse_windows(text: str, start: int) -> list:
    """``"03@44,16"`` -> [("03", 44), ("16", start)]."""
    windows = []
    for item in text.split(","):
        name, _, first = item.strip().partition("@")
        if not name or (first and not first.isdigit()):
            raise SystemExit(f"--sequences: expected NN or NN@START items, got {item!r}")
        windows.append((name, int(first) if first else start))
    return windows


def render_sequences(hia_root: Path, work: Path, windows, frames: int, views: int, seed: int,
                     scale: float = 1.0) -> list:
    """The synthetic multi-view sequences of the (sequence, first frame) ``windows`` (one
    folder each, rendered once)."""
    roots = []
    for s, start in windows:
        size = "" if scale == 1 else f"_x{scale:g}"
        root = work / f"seq{s}_{start}_{frames}_v{views}{size}_seed{seed}"
        if not SequenceLayout(root).info.is_file():
            motion = thesis_motion(hia_root, s, slice(start, start + frames))
            motion = dataclasses.replace(motion, name=f"seq{s}")
            write_synthetic_sequence(with_camera_ring(motion, views, scale), root, noise="none", seed=seed, force=True,
                                     colour="shaded", depth=False, protocol="ballan", progress=False)
        roots.append(root)
    return roots


def score(pred: Path, gt: Path) -> dict:
    """Joint position errors (mm) and bone orientation errors (deg) of the hands, every
    frame; the hand keypoints are the 21 joints of each hand."""
    p, g = read_poses(pred), read_poses(gt)
    hands = [k for k, n in enumerate(g.keypoint_names) if n.split("/")[0].startswith("hand")]
    P, G = p.keypoints_3d[:, 0][:, hands], g.keypoints_3d[:, 0][:, hands]
    joints = np.linalg.norm(P - G, axis=-1)  # (N, J)
    angles = []
    for start in range(0, len(hands), 21):  # each hand's 21 keypoints, in HAND_KEYPOINT_NAMES order
        a, b = np.array(HAND_SKELETON).T + start
        u, v = P[:, b] - P[:, a], G[:, b] - G[:, a]
        cos = (u * v).sum(-1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-9)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    angles = np.concatenate(angles, 1)
    return {"joint_mm": [float(joints.mean()), float(joints.std()), float(joints.max())],
            "bone_deg": [float(angles.mean()), float(angles.std()), float(angles.max())],
            "per_frame_mm": joints.mean(1).round(3).tolist()}


def pooled(parts: list) -> dict:
    """Mean / std / max over the frames of every sequence (weighted by their values)."""
    out = {}
    for key in ("joint_mm", "bone_deg"):
        n = [len(p["per_frame_mm"]) for p in parts]
        mean = sum(p[key][0] * k for p, k in zip(parts, n)) / sum(n)
        var = sum((p[key][1] ** 2 + (p[key][0] - mean) ** 2) * k for p, k in zip(parts, n)) / sum(n)
        out[key] = [mean, var ** 0.5, max(p[key][2] for p in parts)]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hia-root", type=Path, required=True)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--work", type=Path, default=Path("out/exp_multicam"), help="rendered sequences and tracks")
    p.add_argument("--sequences", default=",".join(SEQUENCES), help="comma-separated thesis sequences, each "
                   "NN (from --start) or NN@START")
    p.add_argument("--start", type=int, default=0, help="first frame of the sequences given without @START")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--image-scale", type=float, default=2.0, help="each view's image size over 640x480, the "
                   "same field of view (default 2: 1280x960; the paper's cameras were FullHD, and its noise "
                   "protocol is in their pixels)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rows", default=",".join(label for label, *_ in ROWS), help="comma-separated row labels, or "
                   "none (the HOPE rows alone)")
    p.add_argument("--hope", default="", help="particle counts of the HOPE rows, e.g. 64,128 (slow)")
    p.add_argument("--generations", type=int, default=40, help="of the HOPE rows (the paper: 40)")
    p.add_argument("--min-motion", type=float, default=0.2, help="track --min-motion: convergence, joint motion in mm")
    p.add_argument("--limit-slack", type=limit_slack_arg, default=0.0,
                   help="track --limit-slack: the solver's box, the joint limits widened by this (rad) and grown "
                        "to hold each sequence's first pose; none: no box (the soft limits alone)")
    args = p.parse_args(argv)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    known = [label for label, *_ in ROWS]
    asked = [r for r in args.rows.split(",") if r and r != "none"]
    if any(r not in known for r in asked):
        raise SystemExit(f"--rows: unknown row {next(r for r in asked if r not in known)!r}; rows are "
                         f"{', '.join(known)} (or none, with --hope)")
    rows = [(label, energy, nails, None) for label, energy, nails in ROWS if label in asked]
    counts = [n.strip() for n in args.hope.split(",") if n.strip()]
    if any(not n.isdigit() or int(n) < 1 for n in counts):
        raise SystemExit(f"--hope: expected comma-separated particle counts (e.g. 64,128), got {args.hope!r}")
    rows += [(f"HOPE{n}+ECOS", "E+C+O+S", "auto", int(n)) for n in counts]
    if not rows:
        raise SystemExit("no rows to run: --rows none needs --hope")
    roots = render_sequences(args.hia_root, args.work, parse_windows(args.sequences, args.start), args.frames,
                             args.views, args.seed, args.image_scale)
    table = {}
    for label, energy, nails, particles in rows:
        out = args.work / "tracks" / label.replace("+", "_")
        t0 = time.perf_counter()
        config = TrackerConfig(energy=energy, min_joint_motion=args.min_motion, limit_slack=args.limit_slack)
        if particles is not None:  # the swarm over the same terms
            config = dataclasses.replace(config, solver="pso", particles=particles, generations=args.generations)
        summaries = track_sequences(roots, out, TrackOptions(config, nails=nails), force=True, progress=True)
        seconds = time.perf_counter() - t0
        parts = []
        for root, summary in zip(roots, summaries):
            if summary["status"] != "ok":
                raise RuntimeError(f"{label}: {root}: {summary.get('error')}")
            parts.append({"sequence": root.name, **score(Path(summary["out"]), SequenceLayout(root).gt),
                          "seconds_per_frame": summary["seconds_per_frame"]})
        table[label] = {"energy": energy, "nails": nails, **pooled(parts), "sequences": parts,
                        "seconds_per_frame": seconds / sum(len(q["per_frame_mm"]) for q in parts)}
        print(f"{label}: joints {table[label]['joint_mm'][0]:.2f} mm, bones {table[label]['bone_deg'][0]:.2f} deg, "
              f"{table[label]['seconds_per_frame']:.2f} s/frame", flush=True)
        # after every row, so that a long run (the HOPE rows: minutes a frame) keeps what it finished
        result = {"sequences": [r.name for r in roots], "frames": args.frames, "views": args.views,
                  "image_scale": args.image_scale, "seed": args.seed,
                  "min_motion_mm": args.min_motion, "limit_slack": args.limit_slack,
                  "protocol": "ballan", "complete": len(table) == len(rows), "table": table}
        args.json.write_text(json.dumps(result, indent=1))
    print(markdown(result))
    return 0


def markdown(result: dict) -> str:
    """Table 1's analogue from the JSON of a run."""
    lines = ["| features | joints mean (mm) | std (mm) | max (mm) | bones mean (deg) | std (deg) | max (deg) | s/frame |",
             "|---|---|---|---|---|---|---|---|"]
    for label, t in result["table"].items():
        j, b = t["joint_mm"], t["bone_deg"]
        lines.append(f"| {label} | {j[0]:.2f} | {j[1]:.2f} | {j[2]:.2f} | {b[0]:.2f} | {b[1]:.2f} | {b[2]:.2f} | "
                     f"{t['seconds_per_frame']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
