"""Tracking experiments on renders of the thesis motions (docs/results.md).

    python eval/exp_tracking.py lo --hia-root ../shared/data/hands_in_action --frames 20 --work out/exp --json out/exp_lo.json
    python eval/exp_tracking.py m2d --hia-root ../shared/data/hands_in_action --sequences 09,16 --frames 10 --work out/exp --json out/exp_m2d.json
    python eval/exp_tracking.py ablation --energies LO,LO+C --contact --hia-root ../shared/data/hands_in_action --frames 40 --work out/exp --json out/exp_c.json
    python eval/exp_tracking.py detector-quality --sequences 01,16 --rates 0,0.3,0.6,1 --hia-root ../shared/data/hands_in_action --frames 40 --work out/exp --json out/exp_s_noise.json
    python eval/exp_tracking.py rope --hia-root ../shared/data/hands_in_action --frames 20 --work out/exp --json out/exp_rope.json
    python eval/exp_tracking.py d2m-weight --weights 1,0.25 --hia-root ../shared/data/hands_in_action --frames 40 --work out/exp --json out/exp_d2m_weight.json

``lo``: every sequence with MOTION files is rendered with the kinect noise model
(frames 0..F-1), tracked with LO from its first-frame pose (``gt/`` is not read by
the tracker) and scored; same-scene sequences are tracked as one batch.
``m2d``: model-to-data alone, point-to-point vs point-to-plane, for several
iteration budgets (thesis Table 4.2).
``ablation``: the same as ``lo`` for several energies (thesis Table 4.6), with the
interpenetration of the tracked and the ground-truth poses; ``--contact`` keeps
the sequences with more than one model (hand-hand and hand-object contact),
``--collision-weight`` sets γ_c, and ``--window contact`` renders, per sequence,
the window in which the ground-truth models are closer than 5 mm in most frames.
``detector-quality``: LO+S with simulated fingertip detections following Ballan et
al. (2012, Sec. 5): the projected ground-truth fingertips that the renderer shows
(at least 30 mm^2 visible) are kept with probability ``rate``, 10 % of them add an
outlier uniformly within 200 px, and every detection gets 5 px Gaussian jitter.
These oracle detections are built from ``gt/`` by this script, outside the tracker,
which still reads only the depth.
``rope``: the articulated rope with two hands, rendered with each of ``--noises`` and
tracked with LO. ``--rope-motion pipe`` (default): "Bending a pipe" (sequence 17) with
the rope in the pipe's place, held and bent by the hands
(:func:`rope_from_pipe_sequence`); ``--rope-motion sine``: a thesis two-hand motion
(``--sequences``, e.g. 01) with the rope added over the hands and bending by a
travelling sine (:func:`rope_sequence`); the hands are scored by their keypoints, the
rope by the mean error of its 36 bone origins (its roll about its own axis, which a
tube does not show, does not count).
``d2m-weight``: LO with several weights of the data-to-model term (``--weights``;
the model-to-data weight stays 1), as ``lo`` otherwise.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

import hashlib

import numpy as np

from torchhand.data.synth import SyntheticFrames, thesis_motion, write_synthetic_sequence
from torchhand.data.layout import SequenceLayout, read_depth, read_poses, read_sequence_info
from torchhand.tracking.energies import (DataToModel, ModelToData, Robust, Salient, Weighted, data_to_model,
                                        default_data_to_model, default_priors, parse_energy)
from torchhand.tracking.energies.salient_points import simulated_detector
from torchhand.geometry.render import render
from torchhand.model.fingertips import fingertip_faces
from torchhand.salient.training_data import VISIBLE_MM2, fingertip_targets
from torchhand.model.scene import Scene
from torchhand.scoring.sequences import evaluate_sequence, summarize
from torchhand.io.thesis import FormatError, sequence_models
from torchhand.app.cli import limit_slack_arg
from torchhand.app.runner import TrackOptions, track_sequences
from torchhand.tracking.tracker import TrackerConfig


def contact_window(hia_root: Path, sequence: str, frames: int, near_mm: float = 5.0) -> int:
    """First frame of the ``frames``-long window of a thesis sequence in which most
    frames have two models closer than ``near_mm`` (ground-truth poses)."""
    from scipy.spatial import cKDTree

    fr = thesis_motion(hia_root, sequence, dtype=torch.float32)
    scene = fr.scene
    close = np.zeros(len(fr.theta), bool)
    for k in range(len(fr.theta)):
        with torch.no_grad():
            V = scene(fr.theta[k : k + 1]).vertices[0].numpy()
        parts = [V[s][::4] for s in scene.vertex_slices.values()]
        for a in range(len(parts)):
            for b in range(a + 1, len(parts)):
                if cKDTree(parts[a]).query(parts[b], k=1, distance_upper_bound=near_mm)[0].min() < near_mm:
                    close[k] = True
    counts = np.convolve(close.astype(int), np.ones(frames, int), mode="valid")
    return int(np.argmax(counts)) if len(counts) else 0


def render_sequences(hia_root: Path, seqs, frames: int, work: Path, noise: str = "kinect", window: str = "start"):
    """Render (or reuse) ``frames`` frames of each sequence, from frame 0 or (``window =
    "contact"``) from :func:`contact_window`; returns {seq: folder}."""
    out = {}
    for s in seqs:
        folder = work / (f"hia_{s}_{noise}_{frames}" if window == "start" else f"hia_{s}_{noise}_{frames}_contact")
        if not SequenceLayout(folder).gt.meta.is_file():
            try:
                start = 0 if window == "start" else contact_window(hia_root, s, frames)
                fr = thesis_motion(hia_root, s, slice(start, start + frames), dtype=torch.float32)
            except FormatError:
                print(f"sequence {s}: no MOTION files, skipped")
                continue
            write_synthetic_sequence(fr, folder, noise=noise, seed=int(s), force=True, rgb=False)
        out[s] = folder
    return out


def _sequences(args):
    cfg_dir = args.hia_root / "Configs"
    seqs = args.sequences.split(",") if args.sequences else sorted(p.name for p in cfg_dir.iterdir())
    if args.contact:
        seqs = [s for s in seqs if len(sequence_models(args.hia_root, s)[0]) > 1]
    return seqs


def _prediction_suffix(args) -> str:
    """Output folders of runs with a motion prediction are kept apart from those without."""
    if not args.prediction:
        return ""
    return f"_pred{args.prediction:g}" + ("" if args.prediction_limiter else "_plain")


def track_and_score(args, folders, energy: str, make_terms=None, tag: str = "", labels: str = "proximity") -> dict:
    """Track the rendered sequences with one energy (or the terms of ``make_terms``,
    ``tag`` naming the run) and data labelling, and score them (every model)."""
    cfg = TrackerConfig(energy=energy, metric=args.metric, max_iterations=args.iterations,
                        first_frame_iterations=args.iterations, prediction=args.prediction,
                        prediction_limiter=args.prediction_limiter, labels=labels, limit_slack=args.limit_slack)
    tag = (tag or energy.replace("+", "_")) + ("" if labels == "proximity" else f"_{labels}")
    # the folder names the rendered set too: runs of other windows never share it
    window = "_contact" if getattr(args, "window", "start") == "contact" else ""
    out = args.work / f"tracked_{tag}{_prediction_suffix(args)}_f{args.frames}{window}"
    t0 = time.perf_counter()
    summaries = track_sequences(list(folders.values()), out, TrackOptions(cfg), force=True, make_terms=make_terms)
    elapsed = time.perf_counter() - t0
    results = []
    for s, folder in folders.items():
        r = evaluate_sequence(out / f"hia_{s}", SequenceLayout(folder).gt, with_penetration=args.penetration)
        worst = max(r["per_frame"]["mm"])
        results.append({"sequence": s, "frames": r["frames"], "mean_px": r["thesis_mean_px"], "median_px": r["median_px"],
                        "mean_mm": r["mean_mm"], "median_mm": r["median_mm"], "worst_frame_mm": worst,
                        "lost": worst > 20.0, "penetration": r.get("penetration"),
                        "models": {n: {k: m[k] for k in ("metric", "mean_mm", "worst_frame_mm", "frames_over_20mm")}
                                   for n, m in r["models"].items()},
                        "lost_frames": r["lost_frames"]})
        print(tag, {k: v for k, v in results[-1].items() if k != "penetration"}, flush=True)
    pooled = summarize([evaluate_sequence(out / f"hia_{s}", SequenceLayout(f).gt, with_penetration=False)
                        for s, f in folders.items()])
    return {"energy": energy, "labels": labels, "tag": tag, "prediction": args.prediction,
            "prediction_limiter": args.prediction_limiter, "sequences": results,
            "overall": {k: pooled["thesis_mean_px" if k == "mean_px" else k]
                        for k in ("frames", "mean_px", "median_px", "mean_mm", "median_mm")},
            "track_seconds": elapsed, "tracker": summaries}


def run_lo(args) -> dict:
    folders = render_sequences(args.hia_root, _sequences(args), args.frames, args.work, window=args.window)
    runs = [track_and_score(args, folders, e, labels=lab) for e in (args.energies or "LO").split(",")
            for lab in args.labels.split(",")]
    if len(runs) == 1:
        return {"experiment": "LO on kinect renders", "frames_per_sequence": args.frames, "metric": args.metric,
                "iterations": args.iterations, **{k: v for k, v in runs[0].items() if k != "energy"}}
    return {"experiment": "energies and labellings on kinect renders", "frames_per_sequence": args.frames,
            "metric": args.metric, "iterations": args.iterations, "runs": runs}


def rope_sequence(hia_root: Path, sequence: str, frames: int, work: Path, noise: str, bend: float):
    """A thesis two-hand motion with the articulated rope added: its centroid 40 mm in
    front of the hands' centroid (towards the camera), so both ends lie over the
    hands, turned 0.3 rad in the image plane; each of its 35 joints bends by
    ``bend`` x (its limit, at most 0.3 rad) x a sine travelling along the rope over time."""
    import math

    folder = work / f"rope_{sequence}_{noise}_{frames}_b{bend:g}"
    if SequenceLayout(folder).gt.meta.is_file():
        return folder
    hands = thesis_motion(hia_root, sequence, slice(0, frames), dtype=torch.float32)
    scene = Scene.from_names(list(hands.scene.names) + ["rope"], dtype=torch.float32)
    theta = torch.zeros(len(hands.theta), scene.num_dofs)
    for name in hands.scene.names:
        theta[:, scene.slices[name]] = hands.theta[:, hands.scene.slices[name]]
    rope, r = scene.models[-1], scene.slices["rope"]
    with torch.no_grad():
        centre = hands.scene(hands.theta).vertices.mean(1)
    theta[:, r.start:r.start + 3] = centre + torch.tensor([0.0, 0.0, -40.0]) - rope.vertices_rest.mean(0)
    theta[:, r.start + 5] = 0.3
    lo, hi = scene.lower[r.start + 6:r.stop], scene.upper[r.start + 6:r.stop]
    amp = bend * torch.minimum(hi, -lo).clamp(0, 0.3).nan_to_num(0)
    t = torch.arange(len(theta), dtype=torch.float32)[:, None]
    theta[:, r.start + 6:r.stop] = amp * torch.sin(0.15 * t + torch.linspace(0, 2 * math.pi, r.stop - r.start - 6))
    fr = SyntheticFrames(scene, scene.clamp(theta), hands.cameras, f"rope_{sequence}",
                         {"format": "thesis motion with a rope", "sequence": sequence, "bend": bend})
    write_synthetic_sequence(fr, folder, noise=noise, seed=int(sequence), force=True, rgb=False)
    return folder


def _polyline_points(corners: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Points at arc lengths ``s`` (K,) along polylines ``corners`` (N, C, 3), extended
    along their first and last segments beyond the ends: (N, K, 3)."""
    seg = corners[:, 1:] - corners[:, :-1]
    length = seg.norm(dim=-1)  # (N, C-1)
    cum = torch.cat([torch.zeros_like(length[:, :1]), length.cumsum(1)], 1)  # (N, C)
    i = torch.searchsorted(cum[:, 1:-1].contiguous(), s.expand(len(cum), -1).contiguous())  # segment ids
    a = (s - cum.gather(1, i)) / length.gather(1, i)
    p0 = corners.gather(1, i[..., None].expand(-1, -1, 3))
    d = seg.gather(1, i[..., None].expand(-1, -1, 3))
    return p0 + a[..., None] * d


def rope_from_pipe_sequence(hia_root: Path, frames: int, work: Path, noise: str, sequence: str = "17"):
    """"Bending a pipe" (sequence 17) with the rope in the pipe's place: the hands hold
    and bend the rope as they bent the pipe.

    The rope (449 mm) is centred on the pipe's centre line (two bones of 175 mm, one
    bend joint), 50 mm longer at each end; the target centre line is the pipe's,
    extended along its end segments and rounded at the bend by a Gaussian of 2.5
    bones along the chain. The rope's 76 DoF are fitted to it per frame (bone origins
    and far end, least squares with a small prior on the joint angles), which gives a
    smooth, realistic motion of a held rope: its ends follow the hands, its middle
    bends by up to the pipe's angle."""
    folder = work / f"rope_pipe{sequence}_{noise}_{frames}"
    if SequenceLayout(folder).gt.meta.is_file():
        return folder
    src = thesis_motion(hia_root, sequence, slice(0, frames), dtype=torch.float64)
    names = [n for n in src.scene.names if n != "pipe"]
    scene = Scene.from_names(names + ["rope"], dtype=torch.float64)
    theta = torch.zeros(len(src.theta), scene.num_dofs, dtype=torch.float64)
    for name in names:
        theta[:, scene.slices[name]] = src.theta[:, src.scene.slices[name]]
    pipe, rope = src.scene.model("pipe"), scene.model("rope")

    def chain_points(model, G):  # bone origins and the far end of the last bone
        origins = model.joints_from(G)
        last = model.rest_transforms[-1]  # bones run along their x axis
        end_rest = last[:3, 3] + last[:3, 0] * model.bone_lengths[-1]
        end = (G[:, -1, :3, :3] @ end_rest) + G[:, -1, :3, 3]
        return torch.cat([origins, end[:, None]], 1)

    with torch.no_grad():
        P = chain_points(pipe, src.scene(src.theta).models[src.scene.names.index("pipe")].G)  # (N, 3, 3)
    overhang = (rope.bone_lengths.sum() - (P[:, 1:] - P[:, :-1]).norm(dim=-1).sum(1).mean()) / 2
    step = float(rope.bone_lengths[0])
    k = torch.arange(-8, rope.num_bones + 9, dtype=torch.float64)
    s = k * step - overhang
    target = _polyline_points(P, s)
    w = torch.exp(-0.5 * (torch.arange(-8, 9, dtype=torch.float64) / 2.5) ** 2)
    w = w / w.sum()
    target = torch.nn.functional.conv1d(target.permute(0, 2, 1).reshape(-1, 1, target.shape[1]),
                                        w[None, None]).reshape(len(P), 3, -1).permute(0, 2, 1)  # (N, J+1, 3)

    # Start: the rope straight along the target's first-to-last direction, then fit.
    rest = chain_points(rope, torch.eye(4, dtype=torch.float64).expand(1, rope.num_bones, 4, 4))[0]
    u = (rest[-1] - rest[0]) / (rest[-1] - rest[0]).norm()
    v = (target[:, -1] - target[:, 0]) / (target[:, -1] - target[:, 0]).norm(dim=-1, keepdim=True)
    axis = torch.cross(u.expand_as(v), v, dim=-1)
    angle = torch.atan2(axis.norm(dim=-1), (u * v).sum(-1))
    x = rope.zero_pose(len(P)).double()
    x[:, 3:6] = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12) * angle[:, None]
    x[:, 0:3] = target[:, 0] - rest[0]
    x.requires_grad_(True)
    opt = torch.optim.LBFGS([x], lr=1, max_iter=500, line_search_fn="strong_wolfe", tolerance_grad=1e-9)

    def closure():
        opt.zero_grad()
        err = chain_points(rope, rope(rope.clamp(x), validate=False).G) - target
        loss = (err ** 2).sum() + 10.0 * (x[:, 6:] ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        fitted = rope.clamp(x.detach())
        fit_mm = (chain_points(rope, rope(fitted).G) - target).norm(dim=-1)
    theta[:, scene.slices["rope"]] = fitted
    fr = SyntheticFrames(Scene.from_names(names + ["rope"]), theta.float(), src.cameras, f"rope_pipe{sequence}",
                         {"format": "thesis motion with the rope in the pipe's place", "sequence": sequence,
                          "rope_fit_mm_mean": float(fit_mm.mean()), "rope_fit_mm_max": float(fit_mm.max())})
    write_synthetic_sequence(fr, folder, noise=noise, seed=int(sequence), force=True, rgb=False)
    return folder


def run_rope(args) -> dict:
    """Two hands and the rope: the hands scored by keypoints, the rope by its bone origins;
    one run per noise model, energy (``--energies``) and labelling (``--labels``)."""
    rows = []
    for noise in args.noises.split(","):
        for s in (["17"] if args.rope_motion == "pipe" else _sequences(args)):
            if args.rope_motion == "pipe":
                folder = rope_from_pipe_sequence(args.hia_root, args.frames, args.work, noise, s)
                name = f"tracked_rope_pipe_{noise}_it{args.iterations}{_prediction_suffix(args)}"
            else:
                folder = rope_sequence(args.hia_root, s, args.frames, args.work, noise, args.bend)
                name = f"tracked_rope_{noise}_b{args.bend:g}_it{args.iterations}{_prediction_suffix(args)}"
            for energy in (args.energies or "LO").split(","):
                for labels in args.labels.split(","):
                    cfg = TrackerConfig(energy=energy, metric=args.metric, max_iterations=args.iterations,
                                        first_frame_iterations=args.iterations, prediction=args.prediction,
                                        prediction_limiter=args.prediction_limiter, labels=labels)
                    out = args.work / f"{name}_{energy.replace('+', '_')}_{labels}"
                    t0 = time.perf_counter()
                    track_sequences([folder], out, TrackOptions(cfg), force=True)
                    secs = time.perf_counter() - t0
                    tracked = out / read_sequence_info(folder).name
                    hands = evaluate_sequence(tracked, SequenceLayout(folder).gt, with_penetration=False)
                    gt, pred = read_poses(SequenceLayout(folder).gt), read_poses(tracked)
                    scene = Scene.from_names(gt.models, dtype=torch.float64)
                    with torch.no_grad():
                        joints = [scene.models[-1].joints_from(
                            scene(torch.as_tensor(p.theta, dtype=torch.float64)).models[-1].G) for p in (gt, pred)]
                    per_frame = (joints[0] - joints[1]).norm(dim=-1).mean(1).numpy()
                    rows.append({"sequence": s, "noise": noise, "energy": energy, "labels": labels,
                                 "hands_mean_px": hands["thesis_mean_px"], "hands_mean_mm": hands["mean_mm"],
                                 "rope_joint_mm_mean": float(per_frame.mean()),
                                 "rope_frames_over_20mm": int((per_frame > 20).sum()),
                                 "rope_worst_frame_mm": float(per_frame.max()),
                                 "rope_joint_mm_per_frame": per_frame.tolist(),
                                 "seconds_per_frame": secs / len(per_frame)})
                    print({k: v for k, v in rows[-1].items() if k != "rope_joint_mm_per_frame"}, flush=True)
    return {"experiment": "two hands and the rope", "motion": args.rope_motion, "frames_per_sequence": args.frames,
            "bend": args.bend if args.rope_motion == "sine" else None,
            "iterations": args.iterations, "prediction": args.prediction,
            "prediction_limiter": args.prediction_limiter, "rows": rows}


def run_d2m_weight(args) -> dict:
    folders = render_sequences(args.hia_root, _sequences(args), args.frames, args.work)
    runs = []
    for w in [float(x) for x in args.weights.split(",")]:
        def terms(w=w):
            return [ModelToData(metric=args.metric), Weighted(Robust(DataToModel(), data_to_model.DEFAULT_LOSS), w),
                    *default_priors()]
        runs.append({"d2m_weight": w, **track_and_score(args, folders, "LO", terms, tag=f"LO_d2m{w:g}")})
    return {"experiment": "LO against the data-to-model weight on kinect renders", "frames_per_sequence": args.frames,
            "metric": args.metric, "iterations": args.iterations, "runs": runs}


def run_ablation(args) -> dict:
    folders = render_sequences(args.hia_root, _sequences(args), args.frames, args.work, window=args.window)
    gt_penetration = {}
    if args.penetration:  # the ground truth's own interpenetration, for reference
        for s, f in folders.items():
            r = evaluate_sequence(SequenceLayout(f).gt, SequenceLayout(f).gt)
            gt_penetration[s] = r.get("penetration")
    runs = []
    for e in (args.energies or "LO,LO+C").split(","):
        gc = args.collision_weight if "C" in e[2:] else None
        cs = args.salient_min_score if "S" in e[2:] else None
        labels = args.labels.split(",")[0]
        if gc is None and cs is None:
            runs.append(track_and_score(args, folders, e, labels=labels))
            continue

        def terms(e=e, gc=gc, cs=cs):
            ts = parse_energy(e, args.metric)
            for t in ts:
                if t.name == "collision" and gc is not None:
                    t.weight = gc
                if t.name == "salient" and cs is not None:
                    t.min_score = cs
            return ts
        tag = e.replace("+", "_") + (f"_gc{gc:g}" if gc is not None else "") + (f"_cthr{cs:g}" if cs is not None else "")
        runs.append(track_and_score(args, folders, e, terms, tag=tag, labels=labels))
    if args.physics:  # the thesis' plausibility measure of every run, and of the truth
        window = "_contact" if args.window == "contact" else ""
        runs_out = {r["tag"]: args.work / f"tracked_{r['tag']}{_prediction_suffix(args)}_f{args.frames}{window}"
                    for r in runs}
        for r in runs:
            r["physics_displacement_mm"] = physics_displacement(runs_out[r["tag"]], folders)
        gt_displacement = physics_displacement(None, folders)
    else:
        gt_displacement = None
    return {"experiment": "energy ablation on kinect renders", "frames_per_sequence": args.frames,
            "metric": args.metric, "iterations": args.iterations, "collision_weight": args.collision_weight,
            "salient_min_score": args.salient_min_score, "gt_penetration": gt_penetration,
            "gt_physics_displacement_mm": gt_displacement, "runs": runs}


def physics_displacement(tracked, folders) -> dict:
    """Per sequence with a rigid object, the mean distance its centroid falls in the
    thesis' simulation (35 steps of 0.1 s, the hands static) from each frame's pose:
    ``tracked`` output folder, or the ground truth when None."""
    from torchhand.tracking.simulation import GraspSimulation

    out = {}
    for s, folder in folders.items():
        poses = read_poses(SequenceLayout(folder).gt if tracked is None else tracked / f"hia_{s}")
        scene = Scene.from_names(poses.models, dtype=torch.float64)
        sim = GraspSimulation(scene)
        if not sim.objects:
            continue
        moved = []
        for k in range(len(poses.theta)):
            with torch.no_grad():
                posed = scene(torch.as_tensor(poses.theta[k : k + 1]))
            d = sim.displacement({m: o.vertices[0].numpy() for m, o in enumerate(posed.models)})
            moved.append(float(np.mean(list(d.values()))))
        out[s] = float(np.mean(moved))
    return out


def _depth_key(depth) -> str:
    d = np.asarray(depth.cpu() if isinstance(depth, torch.Tensor) else depth, np.float32)
    return hashlib.sha1(np.ascontiguousarray(d).tobytes()).hexdigest()


def ballan_detections(folder: Path, rate: float, seed: int, fp_rate: float = 0.1, radius: float = 200.0,
                      jitter: float = 5.0) -> dict:
    """Simulated detections of a rendered sequence, keyed by the hash of each raw depth
    frame: {key: (N, 3) rows of u, v, score}."""
    info = read_sequence_info(folder)
    gt = read_poses(SequenceLayout(folder).gt)
    scene = Scene.from_names(gt.models)
    cam = info.cameras[0]
    tips = fingertip_faces(scene)
    rng = np.random.default_rng(seed)
    table = {}
    for k in range(len(gt.theta)):
        with torch.no_grad():
            V = scene(torch.as_tensor(gt.theta[k : k + 1], dtype=torch.float32)).vertices
        rend = render(V, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
        depth = read_depth(SequenceLayout(folder).depth(k), info.depth_unit_mm)
        raw = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        t = fingertip_targets(V, rend.face_id, cam, tips, sensed=torch.as_tensor(raw > 0)[None])
        uv = t.uv[0].numpy()[t.area_mm2[0].numpy() >= VISIBLE_MM2]
        kept = uv[rng.uniform(size=len(uv)) < rate]
        outl = uv[rng.uniform(size=len(uv)) < fp_rate]
        ang, r = rng.uniform(0, 2 * np.pi, len(outl)), radius * np.sqrt(rng.uniform(size=len(outl)))
        outl = outl + np.c_[r * np.cos(ang), r * np.sin(ang)]
        det = np.concatenate([kept, outl]) + rng.normal(0, jitter, (len(kept) + len(outl), 2))
        det = np.clip(det, 0, [cam.width - 1, cam.height - 1])
        table[_depth_key(raw)] = np.c_[det, np.full(len(det), 5.0)]
    return table


def run_detector_quality(args) -> dict:
    folders = render_sequences(args.hia_root, _sequences(args), args.frames, args.work, window=args.window)
    rows = []
    for rate in [float(r) for r in args.rates.split(",")]:
        table = {}
        for k, f in enumerate(folders.values()):
            table.update(ballan_detections(f, rate, seed=k))
        det = simulated_detector(lambda d: table.get(_depth_key(d)))
        cfg = TrackerConfig(energy="LO+S", metric=args.metric, max_iterations=args.iterations,
                            first_frame_iterations=args.iterations, prediction=args.prediction,
                            prediction_limiter=args.prediction_limiter)
        out = args.work / f"tracked_s_rate{rate:g}"
        track_sequences(list(folders.values()), out, TrackOptions(cfg), force=True,
                        make_terms=lambda: [ModelToData(metric=args.metric), default_data_to_model(),
                                            Salient(detector=det), *default_priors()])
        res = summarize([evaluate_sequence(out / f"hia_{s}", SequenceLayout(f).gt, with_penetration=False)
                         for s, f in folders.items()])
        rows.append({"detection_rate": rate, "mean_px": res["thesis_mean_px"], "mean_mm": res["mean_mm"],
                     "median_mm": res["median_mm"]})
        print(rows[-1])
    return {"experiment": "LO+S against simulated detector quality (Ballan et al. 2012 protocol)",
            "sequences": list(folders), "frames_per_sequence": args.frames, "false_positive_rate": 0.1,
            "outlier_radius_px": 200, "jitter_px": 5, "rows": rows}


def run_m2d(args) -> dict:
    seqs = args.sequences.split(",") if args.sequences else ["09", "16"]
    folders = render_sequences(args.hia_root, seqs, args.frames, args.work)
    rows = []
    for metric in ("point-to-point", "point-to-plane"):
        for iters in (5, 10, 15, 20, 30):
            cfg = TrackerConfig(energy="LO", metric=metric, max_iterations=iters, first_frame_iterations=iters,
                                min_joint_motion=0.0, prediction=args.prediction,
                                prediction_limiter=args.prediction_limiter)
            out = args.work / f"tracked_m2d_{metric}_{iters}"
            summaries = track_sequences(list(folders.values()), out, TrackOptions(cfg), force=True, progress=False,
                                        make_terms=lambda: [ModelToData(metric=metric), *default_priors()])
            res = summarize([evaluate_sequence(out / f"hia_{s}", SequenceLayout(f).gt, with_penetration=False)
                             for s, f in folders.items()])
            rows.append({"metric": metric, "iterations": iters, "mean_px": res["thesis_mean_px"], "mean_mm": res["mean_mm"],
                         "seconds_per_frame": sum(s["seconds_per_frame"] for s in summaries) / len(summaries)})
            print(rows[-1])
    return {"experiment": "m2d alone: point-to-point vs point-to-plane", "sequences": seqs,
            "frames_per_sequence": args.frames, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", choices=["lo", "m2d", "ablation", "detector-quality", "d2m-weight", "rope"])
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--sequences", default=None)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--limit-slack", type=limit_slack_arg, default=0.0,
                    help="lo: track --limit-slack, the solver's box: the joint limits widened by this (rad) and "
                         "grown to hold each sequence's first pose; none: no box")
    ap.add_argument("--metric", default="point-to-plane", choices=["point-to-point", "point-to-plane"])
    ap.add_argument("--work", type=Path, default=Path("out/exp"))
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--energies", default=None,
                    help="lo, ablation, rope: comma-separated energies (default: LO; ablation LO,LO+C)")
    ap.add_argument("--labels", default="proximity",
                    help="lo, rope: comma-separated data labellings (proximity, rendered)")
    ap.add_argument("--contact", action="store_true", help="only sequences with more than one model")
    ap.add_argument("--no-penetration", dest="penetration", action="store_false")
    ap.add_argument("--physics", action="store_true",
                    help="ablation: the thesis' physics plausibility measure (object displacement, pybullet)")
    ap.add_argument("--rates", default="0,0.3,0.6,1", help="detector-quality: detection rates")
    ap.add_argument("--weights", default="1,0.25", help="d2m-weight: comma-separated data-to-model weights")
    ap.add_argument("--collision-weight", type=float, default=None,
                    help="ablation: gamma_c of the C term (default: the term's own, 10)")
    ap.add_argument("--noises", default="kinect,none", help="rope: noise models to render with")
    ap.add_argument("--rope-motion", choices=["pipe", "sine"], default="pipe",
                    help="rope: in the pipe's place in sequence 17 (held and bent by the hands), or over the "
                         "hands of --sequences bending by a travelling sine")
    ap.add_argument("--bend", type=float, default=0.25, help="rope, sine: bending amplitude (fraction of the limits)")
    ap.add_argument("--prediction", type=float, default=0.0,
                    help="TrackerConfig.prediction: start each frame from the extrapolated pose (1 = constant velocity; "
                         "default 0, the previous pose, as the experiments in docs/results.md were run; the "
                         "tracker's own default is 1 for hands and rigid objects)")
    ap.add_argument("--no-prediction-limiter", dest="prediction_limiter", action="store_false",
                    help="extrapolate the last step as it is (TrackerConfig.prediction_limiter=False)")
    ap.add_argument("--salient-min-score", type=float, default=None,
                    help="ablation: c_thr of the S term (default: the term's own)")
    ap.add_argument("--window", choices=["start", "contact"], default="start",
                    help="ablation, detector-quality: render from frame 0, or the window where the models touch most")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    result = {"lo": run_lo, "m2d": run_m2d, "ablation": run_ablation,
              "detector-quality": run_detector_quality, "d2m-weight": run_d2m_weight,
              "rope": run_rope}[args.experiment](args)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k not in ("tracker", "runs")}, indent=1)[:4000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
