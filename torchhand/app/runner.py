"""The runner: tracks sequence folders (datasets/README.md layout) and writes the results.

Reading sequence folders, batching same-scene sequences, and writing theta, keypoints,
MOTION files, logs and overlays live here; the tracker itself takes frames and returns
results (:mod:`torchhand.tracking.tracker`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable, List, Optional, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.drawing import depth_to_color, draw_skeleton, write_video
from torchhand.data.layout import Poses, camera_dir, frame_name, read_depth, read_init_pose, read_sequence_info, write_poses
from torchhand.io.assets import THESIS_MODEL_NAMES
from torchhand.io.output_dir import prepare_output_dir
from torchhand.io.thesis import write_motion
from torchhand.model.motion import theta_to_motion
from torchhand.model.scene import Scene
from torchhand.tracking.energies import EnergyTerm
from torchhand.tracking.tracker import Tracker, TrackerConfig, predicted_start

__all__ = ["track_sequences"]


def track_sequences(roots: Sequence, out, config: TrackerConfig = TrackerConfig(), device: str = "cpu",
                    viz: bool = False, force: bool = False, progress: bool = True,
                    make_terms: Optional[Callable[[], List[EnergyTerm]]] = None) -> List[dict]:
    """Track sequence folders (datasets/README.md layout) and write their results.

    Sequences with the same models are solved as one batch, frame by frame; ``gt/``
    is never read. For every sequence ``<out>/<name>/`` receives the ``gt/`` layout
    (theta.npy, keypoints_3d.npy, keypoints_2d.npy, meta.json with per-frame
    ``valid`` flags), ``motion/<Model>.MOTION`` per model (thesis format: row 0 is
    the rigging pose, row k+1 is frame k), ``track_log.json``, and with ``viz``
    overlay PNGs. ``make_terms`` builds custom energy terms per batch (default: from
    ``config.energy``).
    """



    roots = [Path(r) for r in roots]
    infos = [read_sequence_info(r) for r in roots]
    names = [i.name for i in infos]
    if len(set(names)) != len(names):
        names = [f"{i.name}_{k}" for k, i in enumerate(infos)]
    out = Path(out)
    targets = [out / n for n in names]
    for t in targets:
        if t.exists() and any(t.iterdir()) and not force:
            raise FileExistsError(f"{t} is not empty; choose another --out or pass --force")
    groups = {}
    for k, info in enumerate(infos):
        groups.setdefault(tuple(info.models), []).append(k)
    thesis_name = {v: k for k, v in THESIS_MODEL_NAMES.items()}
    summaries = []
    for models, members in groups.items():
        scene = Scene.from_names(list(models), device=device)
        tracker = Tracker(scene, config, make_terms() if make_terms is not None else None)
        init = []
        for k in members:
            th = read_init_pose(roots[k])
            if th.shape != (scene.num_dofs,):
                raise ValueError(f"{roots[k] / 'init_pose.json'}: theta has {th.size} values, the scene "
                                 f"{list(models)} has {scene.num_dofs} DoF")
            init.append(th)
        theta = torch.as_tensor(np.stack(init), dtype=torch.float32, device=device)
        n_frames = max(infos[k].frames for k in members)
        cams = [infos[k].cameras[0].to(device) for k in members]
        thetas, valids, logs = [], [], []
        history = []  # (theta, tracked) of the last three frames, oldest first
        generator = torch.Generator().manual_seed(config.seed)
        bar = tqdm(total=n_frames * len(members), desc=f"track {'+'.join(models)}", unit="frame", disable=not progress)
        for f in range(n_frames):
            depths = []
            for k in members:
                path = camera_dir(roots[k], 0) / "depth" / frame_name(f)
                if f >= infos[k].frames:
                    depths.append(None)
                    continue
                try:
                    depths.append(read_depth(path, infos[k].depth_unit_mm))
                except ValueError as err:  # missing or unreadable frame: keep the previous pose
                    tqdm.write(f"warning: {err}; keeping the previous pose")
                    depths.append(None)
            t0 = time.perf_counter()
            start = predicted_start(history, config.prediction, config.prediction_limiter)
            res = tracker.track_frame(depths, cams, theta, first=(f == 0), generator=generator, start=start)
            dt = time.perf_counter() - t0
            theta = res.theta
            history = (history + [(theta, res.valid.to(theta.device))])[-3:]
            thetas.append(theta.detach().cpu().numpy())
            valids.append(res.valid.numpy())
            for i, note in enumerate(res.notes):
                if note:
                    tqdm.write(f"{names[members[i]]} frame {f}: {note}")
            logs.append({"frame": f, "seconds": dt, "iterations": res.iterations.tolist(), "notes": res.notes,
                         "energy": [None if not np.isfinite(e) else float(e) for e in res.energy.tolist()],
                         "valid": res.valid.tolist(), "recovered": res.recovered.tolist()})
            bar.update(len(members))
        bar.close()
        TH = np.stack(thetas, 1)  # (S, N, D)
        with torch.no_grad():
            for i, k in enumerate(members):
                N = infos[k].frames
                th = torch.as_tensor(TH[i, :N], device=device)
                posed = scene(th)
                cam = cams[i]
                kp3 = cam.to_camera(posed.keypoints).cpu().numpy()[:, None]
                kp2 = cam.project(posed.keypoints).cpu().numpy()[:, None]
                target = prepare_output_dir(targets[k], force)
                valid = np.stack(valids, 1)[i, :N]
                write_poses(target, Poses(TH[i, :N].astype(np.float64), kp3, kp2, list(scene.names),
                                          scene.dof_names, scene.keypoint_names, valid))
                (target / "motion").mkdir()
                for name, model in zip(scene.names, scene.models):
                    mot = theta_to_motion(model, th[:, scene.slices[name]])
                    rest = {b: model.rest_transforms[j].cpu().double().numpy()[None] for j, b in enumerate(model.bone_names)}
                    mot = {b: np.concatenate([rest[b], m], 0) for b, m in mot.items()}
                    write_motion(target / "motion" / f"{thesis_name.get(name, name)}.MOTION", mot)
                log = [{"frame": e["frame"], "seconds": e["seconds"], **{key: e[key][i] for key in
                        ("iterations", "energy", "valid", "recovered", "notes")}} for e in logs[:N]]
                (target / "track_log.json").write_text(json.dumps({"sequence": names[k], "source": str(roots[k]),
                                                                    "energy": config.energy, "frames": log}))
                if viz:
                    _write_overlays(target, roots[k], infos[k], scene, posed, cam)
                secs = [e["seconds"] for e in logs[:N]]
                summaries.append({"sequence": names[k], "frames": N, "out": str(target),
                                  "seconds_per_frame": float(np.mean(secs)) / len(members),
                                  "flagged_frames": int((~valid).sum())})
    return summaries


def _write_overlays(target, root, info, scene, posed, cam):
    """Tracked skeletons over the input depth, one PNG per frame, and an MP4."""

    (target / "overlays").mkdir()
    images = []
    hands = [k for k, m in enumerate(scene.models) if m.kind == "hand"]
    for f in range(info.frames):
        img = depth_to_color(read_depth(camera_dir(root, 0) / "depth" / frame_name(f), info.depth_unit_mm))
        for k in hands:
            draw_skeleton(img, cam.project(posed.models[k].keypoints[f : f + 1])[0].cpu().numpy())
        cv2.imwrite(str(target / "overlays" / frame_name(f)), img)
        images.append(img)
    write_video(images, target / "overlays.mp4")
