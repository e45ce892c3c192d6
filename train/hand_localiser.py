"""Train the hand localiser (torchhand.salient.localiser_net.LocaliserNet) on rendered hands
in context (torchhand.salient.localiser_data): per-pixel classes (background, left
hand, right hand, arm and body), the 21 standard joints of each hand, handedness.

    python -m train.hand_localiser --out runs/localiser [--config cfg.json] [--cache DIR] [--force] [--resume]

The loop, checkpoints, exact ``--resume``, ``--stop-at``, the log and DDP are those of
every detector of the project (:mod:`train.trainer`); this module is the task:

1. frames: ``train_frames`` renders with the Kinect noise model, their finger poses a
   third from the thesis motions of ``train_sequences`` (when the thesis data is at
   hand), the rest random and curled; validation: ``val_frames`` renders of another
   seed with the independent active-stereo noise model and the thesis motions of
   ``val_sequences`` (the benchmark's test set uses a third seed,
   ``eval/exp_localiser.py``). Rendered once, cached under a hash of the data fields;
   ``extra_train_data`` adds the training frames of other data fields (e.g. an earlier
   run's seed, read from its cache).
2. batches: a share ``p_crop`` of the samples are a hand's box widened 1.3-2x (the
   crop pass), the rest a 128 px window of the frame reduced 4-6x (the frame pass);
   mirror flips swap the left and right hand (a mirrored right hand is a left hand);
   a share ``p_background`` are composited onto real depth frames whose own hands are
   removed (``backgrounds``, :func:`composite`); a hand with fewer than 30 pixels left
   in a sample (range cut, hidden) has no joint targets there.
3. loss: cross-entropy of the classes (hands weighted ``hand_weight``), the
   penalty-reduced focal loss of the joints' heat maps (Gaussian targets), L1 on the
   joints' sub-cell offsets and relative depths at their cells.
4. writes ``RUN/hand_localiser.pt`` and ``RUN/hand_localiser.onnx``; validation logs
   the hand-pixel IoU, the median 2D joint error (px, crop pass) and the handedness
   accuracy, and with ``real_val`` the real frames' figures (:func:`evaluate_real`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import List, NamedTuple

import cv2
import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from tqdm import tqdm

from torchhand.salient.localiser_net import STRIDE, LocaliserConfig, LocaliserNet, export_localiser_onnx
from torchhand.salient.localiser_data import (IGNORE, ContextConfig, LocaliserFrames, concat_localiser_frames,
                                              load_localiser_frames, render_context_frames, save_localiser_frames)
from train.trainer import RunConfig, Task, main as run_main

#: Version of the rendered frames: caches of another version are rendered again.
DATA_VERSION = 1
WEIGHT_NAME = "hand_localiser"


@dataclass
class LocaliserTrainConfig(RunConfig):
    """A localiser run (``--config`` JSON overrides fields)."""

    steps: int = 4000
    batch_size: int = 24
    lr: float = 3e-3
    checkpoint_every: int = 150
    # --- data (a change re-renders)
    train_frames: int = 2400
    val_frames: int = 160
    data_seed: int = 11
    val_seed: int = 5011
    train_sequences: List[str] = field(default_factory=lambda: [
        "01", "02", "04", "06", "08", "09", "11", "12", "13", "15", "16", "17", "19"])
    val_sequences: List[str] = field(default_factory=lambda: ["03", "10", "20"])
    # --- network
    network: dict = field(default_factory=dict)  # LocaliserConfig fields
    # --- batches and loss
    p_crop: float = 0.7
    crop_widen: List[float] = field(default_factory=lambda: [1.3, 2.0])
    frame_scale: List[float] = field(default_factory=lambda: [0.17, 0.3])
    heat_sigma: float = 1.0  # cells
    hand_weight: float = 3.0
    heat_weight: float = 1.0
    offset_weight: float = 0.5
    depth_weight: float = 0.5
    far_cut_mm: List[float] = field(default_factory=lambda: [900.0, 4000.0])  # random range cut-off (augmentation)
    # --- more training renders: each entry overrides some of ``EXTRA_DATA_FIELDS`` (its
    # own cache); its frames join the training set (e.g. an earlier run's renders)
    extra_train_data: List[dict] = field(default_factory=list)
    # --- real context (:mod:`train.real_backgrounds`): each entry is a folder of real
    # depth frames, {"frames", "depth_unit_mm", "focal_px", "hand_masks"}; a share
    # ``p_background`` of the samples are rendered hands composited onto one of them
    backgrounds: List[dict] = field(default_factory=list)
    p_background: float = 0.0
    background_behind_mm: List[float] = field(default_factory=lambda: [100.0, 700.0])  # its median behind the hand
    # "behind_hand" (above), or "recorded": the real frame moved by ``background_shift_mm``
    # from its recorded depth, the rendered hands drawn over it wherever they are (the
    # placement of the shipped network's run, train/configs/localiser_real.json)
    background_placement: str = "behind_hand"
    background_shift_mm: List[float] = field(default_factory=lambda: [-150.0, 500.0])
    # real frames of the same form whose hand validation must find (and nothing else)
    real_val: dict = field(default_factory=dict)

    def data_key(self) -> str:
        d = {"version": DATA_VERSION, **{k: getattr(self, k) for k in (
            "train_frames", "val_frames", "data_seed", "val_seed", "train_sequences", "val_sequences")}}
        return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


#: The data fields an ``extra_train_data`` entry may set.
EXTRA_DATA_FIELDS = ("train_frames", "data_seed", "train_sequences")
#: The fields of a ``backgrounds`` or ``real_val`` entry.
REAL_FIELDS = ("frames", "depth_unit_mm", "focal_px", "hand_masks")


def real_frames(entry: dict):
    """The :class:`train.real_backgrounds.RealFrames` of a ``backgrounds`` entry."""
    from train.real_backgrounds import read_real_frames

    return read_real_frames(entry["frames"], entry["depth_unit_mm"], entry["focal_px"], entry["hand_masks"])


def thesis_articulations(hia_root: Path, sequences: List[str], per_sequence: int = 48) -> dict:
    """Per shipped hand model, the finger articulations (M, D - 6) of the thesis motions
    of ``sequences``, ``per_sequence`` evenly spaced frames of each (empty without the
    thesis data)."""
    from torchhand.io.thesis import sequence_models

    from torchhand.data.synth import thesis_motion
    from torchhand.io.thesis import FormatError

    rows = {}
    for s in sequences:
        try:
            n = sequence_models(hia_root, s)[1].total_aligned
            fr = thesis_motion(hia_root, s, frames=slice(0, n, max(1, n // per_sequence)), dtype=torch.float32)
        except (FormatError, FileNotFoundError, OSError, ValueError):
            continue
        for name in fr.scene.names:
            if name in ("hand_left", "hand_right"):
                sl = fr.scene.slices[name]
                rows.setdefault(name, []).append(fr.theta[:, sl.start + 6:sl.stop])
    return {k: torch.cat(v) for k, v in rows.items()}


# ------------------------------------------------------------------------- batches


def _window(image: np.ndarray, centre: tuple, side: float, size: int, flip: bool, fill) -> np.ndarray:
    """The square window of ``side`` px around ``centre`` (u, v), resized to ``size``
    (nearest: no depth mixed across edges), mirrored with ``flip``."""
    s = size / side
    u0, v0 = centre[0] - side / 2, centre[1] - side / 2
    M = np.array([[s, 0, -u0 * s + 0.5 * s - 0.5], [0, s, -v0 * s + 0.5 * s - 0.5]], np.float32)
    if flip:
        M[0] = -M[0]
        M[0, 2] += size - 1
    return cv2.warpAffine(image, M, (size, size), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=fill)


class Background(NamedTuple):
    """A real frame to composite onto (:func:`background`): depth (H, W) mm with its hand
    removed, its camera's focal length (px), the median of its measured depths (mm) and
    the (row, column) of every 8th measured pixel in both directions."""

    depth: np.ndarray
    focal_px: float
    median_mm: float
    points: np.ndarray


def background(depth: np.ndarray, focal_px: float) -> Background:
    """The :class:`Background` of a frame, its statistics computed once."""
    valid = depth > 0
    return Background(depth, float(focal_px), float(np.median(depth[valid])) if valid.any() else float("nan"),
                      np.argwhere(valid[::8, ::8]) * 8)


def composite(d: np.ndarray, lab: np.ndarray, hand_z, bg: Background, side: float, render_focal: float,
              r: np.ndarray, behind_mm: tuple, recorded: tuple = ()) -> tuple:
    """A rendered sample window (depth ``d`` (S, S) mm, classes ``lab`` (S, S)) with a
    real frame behind it (``bg``) at the same metric scale: (depth, classes) of the composite.

    The real frame is moved in depth so that its median lies a share ``r[0]`` of
    ``behind_mm`` behind the hand (``hand_z`` mm; None: the window's hand pixels', else
    its measured pixels' median), and its window is the render's ``side`` scaled by the
    focal lengths' ratio and by that move (exact at its median depth); it is mirrored
    (``r[4]``) and centred near a random measured pixel (``r[1:4]``). The rendered hands,
    arm and body, and other rendered things within 200 mm of the hand, stay where nearer
    than the real frame (a real arm may hide a hand); every other pixel is the real
    frame's, labelled body where measured (every measured pixel of a background must be
    the person or nearer than the hand's surroundings: walls would be taught as body).
    With ``recorded`` (low, high) mm, the real frame is moved by a share ``r[0]`` of it
    from its recorded depth instead, and the rendered hands are drawn over it wherever
    they are."""
    S = d.shape[0]
    pts, z_med = bg.points, bg.median_mm
    hand = (lab == 1) | (lab == 2)
    if hand_z is None and (hand.any() or not recorded):
        seen = d[hand] if hand.any() else d[d > 0]
        hand_z = float(np.median(seen)) if len(seen) else None
    if not len(pts) or (hand_z is None and not recorded):
        return d, lab
    shift = (recorded[0] + (recorded[1] - recorded[0]) * r[0] if recorded else
             hand_z + behind_mm[0] + (behind_mm[1] - behind_mm[0]) * r[0] - z_med)
    side_r = side * bg.focal_px / render_focal * (z_med + shift) / z_med
    v, u = pts[int(r[1] * len(pts)) % len(pts)]
    centre = (u + (r[2] - 0.5) * side_r / 2, v + (r[3] - 0.5) * side_r / 2)
    real = _window(bg.depth, centre, side_r, S, r[4] < 0.5, 0.0)
    real = np.where(real > 0, real + np.float32(shift), np.float32(0.0))
    real[real <= 0] = 0.0
    near = hand | (lab == 3)
    if hand_z is not None:
        near |= (lab == 0) & (np.abs(d - hand_z) < 200.0)
    keep = near & (d > 0) & ((real == 0) | (d <= real))
    if recorded:
        keep |= hand
    return (np.where(keep, d, real).astype(np.float32),
            np.where(keep, lab, np.where(real > 0, 3, IGNORE)).astype(lab.dtype))


def sample_batch(data: LocaliserFrames, cfg: LocaliserTrainConfig, g: torch.Generator, part: tuple = (0, 1),
                 backgrounds: tuple = ()) -> tuple:
    """One step's samples: (depth (B, 1, S, S) mm, reference (B,), labels (B, S, S) int64,
    joints (B, 2, 21, 3) [u, v, z] in input px / mm, NaN absent); ``part``: this rank's
    share of the batch (the draws are those of the whole batch); ``backgrounds``: the
    :class:`Background` s of real frames to composite a share ``cfg.p_background`` of
    the samples onto (:func:`composite`)."""
    S = LocaliserConfig(**cfg.network).input_size
    B = cfg.batch_size
    N = len(data.depth)
    idx = torch.randint(0, N, (B,), generator=g).numpy()
    draws = torch.rand(B, 8, generator=g).numpy()
    real_draws = torch.rand(B, 7, generator=g).numpy() if backgrounds else None
    rank, world = part
    share = range(rank * B // world, (rank + 1) * B // world)
    depth = np.zeros((len(share), 1, S, S), np.float32)
    ref = np.zeros(len(share), np.float32)
    labels = np.full((len(share), S, S), IGNORE, np.int64)
    joints = np.full((len(share), 2, 21, 3), np.nan, np.float32)
    H, W = data.depth.shape[1:]
    for i, b in enumerate(share):
        f, r = idx[b], draws[b]
        present = np.nonzero(np.isfinite(data.joints_z[f]).all(1))[0]
        uv = data.joints_uv[f]
        if r[0] < cfg.p_crop and len(present):
            k = present[int(r[1] * len(present)) % len(present)]
            lo, hi = np.nanmin(uv[k], 0), np.nanmax(uv[k], 0)
            side = max(float((hi - lo).max()), 16.0) * (cfg.crop_widen[0] + (cfg.crop_widen[1] - cfg.crop_widen[0]) * r[2])
            centre = ((lo + hi) / 2 + (r[3:5] - 0.5) * 0.3 * side)
            hand_z = float(np.nanmedian(data.joints_z[f, k]))
        else:
            scale = cfg.frame_scale[0] + (cfg.frame_scale[1] - cfg.frame_scale[0]) * r[2]
            side = S / scale
            centre = np.array([W * r[3], H * r[4]])
            hand_z = None
        flip = r[5] < 0.5
        d = _window(data.depth[f].astype(np.float32), tuple(centre), side, S, flip, 0.0)
        lab = _window(data.labels[f], tuple(centre), side, S, flip, 0).astype(np.int64)
        if real_draws is not None and real_draws[b, 0] < cfg.p_background:
            bg = backgrounds[int(real_draws[b, 1] * len(backgrounds)) % len(backgrounds)]
            d, lab = composite(d, lab, hand_z, bg, side, float(data.K[f, 0, 0]), real_draws[b, 2:],
                               tuple(cfg.background_behind_mm), tuple(cfg.background_shift_mm)
                               if cfg.background_placement == "recorded" else ())
        cut = cfg.far_cut_mm[0] + (cfg.far_cut_mm[1] - cfg.far_cut_mm[0]) * r[6]
        d[d > cut] = 0.0
        lab[(d == 0) & (lab != IGNORE)] = IGNORE
        # a hand hidden (by the range cut, or by a real arm or body in front of it) has
        # no joints to find
        hidden = np.array([(lab == 1).sum() < 30, (lab == 2).sum() < 30])
        if flip:
            lab = np.where(lab == 1, 2, np.where(lab == 2, 1, lab))
        s = S / side
        ju = (uv[..., 0] - (centre[0] - side / 2) + 0.5) * s - 0.5
        jv = (uv[..., 1] - (centre[1] - side / 2) + 0.5) * s - 0.5
        if flip:
            ju = S - 1 - ju
        jt = np.where(hidden[:, None, None], np.nan, np.stack([ju, jv, data.joints_z[f]], -1))
        joints[i] = jt[::-1] if flip else jt
        valid = d[d > 0]
        ref[i] = (hand_z + 40.0 * (r[7] - 0.5)) if hand_z is not None else (float(np.median(valid)) if len(valid) else 1000.0)
        depth[i, 0] = d
        labels[i] = lab
    return torch.from_numpy(depth), torch.from_numpy(ref), torch.from_numpy(labels), torch.from_numpy(joints)


def targets(joints: torch.Tensor, ref: torch.Tensor, size: int, cfg: LocaliserTrainConfig) -> tuple:
    """Heat-map targets (B, 21, h, w) (the joints of both hands share a channel: the
    larger Gaussian wins), the positive cells (B, 21, h, w) bool, offset targets (B, 42,
    h, w) and depth targets (B, 21, h, w) at stride 2."""
    B = joints.shape[0]
    h = w = size // STRIDE
    J = joints.reshape(B, 42, 3)
    pc = (J[..., :2] + 0.5) / STRIDE - 0.5  # cell coordinates
    inside = torch.isfinite(pc).all(-1) & (pc[..., 0] > -0.5) & (pc[..., 0] < w - 0.5) & (pc[..., 1] > -0.5) & (pc[..., 1] < h - 0.5)
    pc = torch.nan_to_num(pc, nan=-100.0)
    cell = pc.round().clamp(0, w - 1).long()
    xs = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w)
    ys = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1)
    g = torch.exp(-((xs - pc[..., 0, None, None]) ** 2 + (ys - pc[..., 1, None, None]) ** 2) / (2 * cfg.heat_sigma ** 2))
    g = (g * inside[..., None, None]).reshape(B, 2, 21, h, w).amax(1)
    pos = torch.zeros(B, 21, h, w, dtype=torch.bool)
    b_i, j_i = torch.nonzero(inside, as_tuple=True)
    c_i = j_i % 21
    pos[b_i, c_i, cell[b_i, j_i, 1], cell[b_i, j_i, 0]] = True
    heat = torch.where(pos, torch.ones_like(g), g)
    off = torch.zeros(B, 42, h, w)
    dep = torch.zeros(B, 21, h, w)
    delta = pc - cell.float()
    rel = (J[..., 2] - ref[:, None]) / LocaliserConfig(**cfg.network).relative_scale_mm
    off[b_i, 2 * c_i, cell[b_i, j_i, 1], cell[b_i, j_i, 0]] = delta[b_i, j_i, 0]
    off[b_i, 2 * c_i + 1, cell[b_i, j_i, 1], cell[b_i, j_i, 0]] = delta[b_i, j_i, 1]
    dep[b_i, c_i, cell[b_i, j_i, 1], cell[b_i, j_i, 0]] = torch.nan_to_num(rel[b_i, j_i])
    return heat, pos, off, dep


def loss_fn(out, labels, heat, pos, off, dep, cfg: LocaliserTrainConfig, npos: torch.Tensor, size: int = 1) -> tuple:
    """(total, parts): class cross-entropy (this rank's mean / ``size``: the ranks' sum is
    the batch mean), focal heat loss, offset and depth L1 (by the batch's positives)."""
    logits = F.interpolate(out.classes, size=labels.shape[-2:], mode="bilinear", align_corners=False)
    w = torch.tensor([1.0, cfg.hand_weight, cfg.hand_weight, 1.0], device=logits.device)
    cls = F.cross_entropy(logits, labels, weight=w, ignore_index=IGNORE) / size
    p = torch.sigmoid(out.heat).clamp(1e-4, 1 - 1e-4)
    n = npos.clamp_min(1.0)
    posf = pos.float()
    focal = -(posf * (1 - p) ** 2 * torch.log(p) + (1 - posf) * (1 - heat) ** 4 * p ** 2 * torch.log(1 - p)).sum() / n
    pos2 = pos.repeat_interleave(2, dim=1).float()
    offset = (F.l1_loss(out.offset, off, reduction="none") * pos2).sum() / n
    depth = (F.smooth_l1_loss(out.depth, dep, reduction="none", beta=0.1) * posf).sum() / n
    total = cls + cfg.heat_weight * focal + cfg.offset_weight * offset + cfg.depth_weight * depth
    return total, {"loss": total.detach(), "cls": cls.detach(), "heat": focal.detach(), "offset": offset.detach(),
                   "depth": depth.detach()}


# ---------------------------------------------------------------------- validation


def evaluate(net: LocaliserNet, data: LocaliserFrames) -> dict:
    """Hand-pixel IoU (mean over frames), median 2D joint error (px) of the found hands
    against their side's ground truth, handedness accuracy and share of hands found,
    with the whole two-pass localiser on full frames."""
    from torchhand.salient.localiser import HandLocaliser

    was = net.training
    loc = HandLocaliser.from_net(net.eval())
    ious, errs, right_side, found, total = [], [], 0, 0, 0
    for f in range(len(data.depth)):
        res = loc.locate(data.depth[f])
        gt = data.labels[f]
        known = gt != IGNORE
        pred_h = np.isin(res.labels, (1, 2)) & known
        gt_h = np.isin(gt, (1, 2)) & known
        if gt_h.sum():
            ious.append((pred_h & gt_h).sum() / max((pred_h | gt_h).sum(), 1))
        for k, side in enumerate(("left", "right")):
            if not np.isfinite(data.joints_z[f, k]).all():
                continue
            total += 1
            hands = [h for h in res.hands if np.nanmean(np.linalg.norm(h.uv - data.joints_uv[f, k], axis=1)) < 60]
            if hands:
                found += 1
                right_side += hands[0].side == side
                errs.append(np.linalg.norm(hands[0].uv - data.joints_uv[f, k], axis=1))
    net.train(was)
    e = np.concatenate(errs) if errs else np.array([np.nan])
    return {"val_iou": float(np.mean(ious)) if ious else float("nan"), "val_px_median": float(np.median(e)),
            "val_handedness": right_side / max(found, 1), "val_found": found / max(total, 1)}


def evaluate_real(net: LocaliserNet, real) -> dict:
    """On real frames with reference hand masks (:class:`train.real_backgrounds.RealFrames`):
    the share of frames whose most confident hand lies mostly (half its pixels) on the
    reference hand, the mean share of the hand pixels found off it (an arm, the body, the
    head taken for a hand), and the mean hand-pixel IoU (the masks include some wrist)."""
    from torchhand.salient.localiser import HandLocaliser

    was = net.training
    loc = HandLocaliser.from_net(net.eval())
    found, off, iou = [], [], []
    for d, ref in zip(real.depth, real.hands):
        res = loc.locate(d)
        pred = np.isin(res.labels, (1, 2))
        found.append(bool(res.hands) and (res.hands[0].mask & ref).sum() >= 0.5 * res.hands[0].mask.sum())
        off.append((pred & ~ref).sum() / max(pred.sum(), 1))
        iou.append((pred & ref).sum() / max((pred | ref).sum(), 1))
    net.train(was)
    return {"real_found": float(np.mean(found)), "real_off_hand": float(np.mean(off)), "real_iou": float(np.mean(iou))}


# ------------------------------------------------------------------------ the task


def _rendered(cfg: LocaliserTrainConfig, split: str, hia_root: Path, cache: Path) -> LocaliserFrames:
    """The ``split`` frames of ``cfg``'s data fields: rendered (and cached under their
    hash), or read from the cache."""
    d = cache / f"localiser_{cfg.data_key()}"
    d.mkdir(parents=True, exist_ok=True)
    if (d / f"{split}.npz").is_file():  # each split is written whole (renamed into place)
        print(f"reusing rendered {split} frames from {d}")
        return load_localiser_frames(d / f"{split}.npz")
    n, seed, seqs, noise = ((cfg.train_frames, cfg.data_seed, cfg.train_sequences, "kinect") if split == "train" else
                            (cfg.val_frames, cfg.val_seed, cfg.val_sequences, "stereo"))
    motions = thesis_articulations(hia_root, seqs)
    parts = []
    chunk = 200
    for s in tqdm(range(0, n, chunk), desc=f"render {split}", unit="chunk"):
        parts.append(render_context_frames(min(chunk, n - s), seed * 1000 + s, ContextConfig(noise=noise),
                                           motions, progress=False, name=split))
    frames = concat_localiser_frames(parts)
    tmp = d / f"{split}.tmp.npz"
    save_localiser_frames(frames, tmp)
    tmp.rename(d / f"{split}.npz")
    return frames


class LocaliserTask(Task):
    name = "localiser"
    config_type = LocaliserTrainConfig

    def check_config(self, cfg) -> None:
        LocaliserConfig(**cfg.network)
        if not 0 <= cfg.p_crop <= 1:
            raise ValueError(f"p_crop must be in [0, 1], got {cfg.p_crop}")
        for extra in [{}] + list(cfg.extra_train_data):
            unknown = sorted(set(extra) - set(EXTRA_DATA_FIELDS))
            if unknown:
                raise ValueError(f"extra_train_data: unknown fields {unknown}; "
                                 f"expected some of {list(EXTRA_DATA_FIELDS)}")
            if sorted(set(extra.get("train_sequences", cfg.train_sequences)) & set(cfg.val_sequences)):
                raise ValueError("train_sequences and val_sequences overlap")
        for name, entries in (("backgrounds", cfg.backgrounds), ("real_val", [cfg.real_val] if cfg.real_val else [])):
            for e in entries:
                if sorted(e) != sorted(REAL_FIELDS):
                    raise ValueError(f"{name}: expected the fields {list(REAL_FIELDS)}, got {sorted(e)}")
                for key in ("frames", "hand_masks"):
                    if not Path(e[key]).exists():
                        raise ValueError(f"{name}: {key} {e[key]} not found")
        for name in ("background_behind_mm", "background_shift_mm"):
            lo_hi = list(getattr(cfg, name))
            if len(lo_hi) != 2 or lo_hi[0] > lo_hi[1]:
                raise ValueError(f"{name} must be [low, high] in mm, got {lo_hi}")
        if cfg.background_placement not in ("behind_hand", "recorded"):
            raise ValueError(f"background_placement must be 'behind_hand' or 'recorded', got {cfg.background_placement!r}")
        if not 0 <= cfg.p_background <= 1 or (cfg.p_background > 0 and not cfg.backgrounds):
            raise ValueError(f"p_background must be in [0, 1] and needs backgrounds, got {cfg.p_background}")
        if cfg.real_val and any(Path(cfg.real_val["frames"]).resolve() == Path(e["frames"]).resolve()
                                for e in cfg.backgrounds):
            raise ValueError("real_val's frames are among the backgrounds: validate on other frames")

    def build_net(self) -> LocaliserNet:
        return LocaliserNet(LocaliserConfig(**self.cfg.network))

    def start_from(self, net: LocaliserNet, start: LocaliserNet, path: str) -> None:
        """The same network, or a narrower one widened (:meth:`LocaliserNet.widen_from`)."""
        if start.config == net.config:
            net.load_state_dict(start.state_dict())
            return
        try:
            net.widen_from(start)
        except ValueError as e:
            raise SystemExit(f"{path}: {e}") from None
        print(f"{path}: widened from {start.config.channels}/{start.config.decoder} to "
              f"{net.config.channels}/{net.config.decoder}")

    def datasets(self, hia_root: Path, cache: Path) -> tuple:
        cfg = self.cfg
        train = [_rendered(cfg, "train", hia_root, cache)]
        for extra in cfg.extra_train_data:
            train.append(_rendered(replace(cfg, **extra), "train", hia_root, cache))
        train = train[0] if len(train) == 1 else concat_localiser_frames(train)
        self.backgrounds = []
        for e in cfg.backgrounds:
            real = real_frames(e)
            self.backgrounds += [background(d, real.focal_px) for d in real.without_hands()]
        self.real_val = real_frames(cfg.real_val) if cfg.real_val else None
        return train, _rendered(cfg, "val", hia_root, cache)

    def describe_data(self, train, val) -> str:
        real = f", {len(self.backgrounds)} real backgrounds" if self.backgrounds else ""
        real += f", {len(self.real_val.depth)} real val" if self.real_val is not None else ""
        return f"frames: {len(train.depth)} train, {len(val.depth)} val{real}"

    def batch(self, data, g: torch.Generator, part: tuple) -> tuple:
        return sample_batch(data, self.cfg, g, part, tuple(self.backgrounds))

    def loss(self, model, batch: tuple, device, size: int) -> tuple:
        depth, ref, labels, joints = batch
        heat, pos, off, dep = targets(joints, ref, depth.shape[-1], self.cfg)
        depth, ref, labels, heat, pos, off, dep = (x.to(device) for x in (depth, ref, labels, heat, pos, off, dep))
        npos = pos.float().sum()
        if size > 1:  # normalised by the whole batch's positives (see train.trainer)
            dist.all_reduce(npos)
        return loss_fn(model(depth, ref), labels, heat, pos, off, dep, self.cfg, npos, size)

    def validate(self, net, val) -> dict:
        real = evaluate_real(net, self.real_val) if self.real_val is not None else {}
        return {**evaluate(net, val), **real}

    def finish(self, net, out: Path, val) -> dict:
        net.save(out / f"{WEIGHT_NAME}.pt")
        export_localiser_onnx(net, out / f"{WEIGHT_NAME}.onnx")
        return self.validate(net, val)


def main(argv=None) -> int:
    return run_main(LocaliserTask, argv, doc=__doc__)


if __name__ == "__main__":
    import sys

    sys.exit(main())
