"""Train the salient point detector (torchhand.salient.SalientNet): fingertips on
rendered depth (the default), or finger nails on rendered colour (``"modality":
"colour"``, Ballan et al. 2012; ``train/configs/nails_rgb.json``).

    python -m train.salient_detector --out runs/salient [--config cfg.json] [--cache DIR] [--force] [--resume]

1. Renders (or reuses from the cache) training frames: the thesis motions of the
   training sequences, random poses within the joint limits of one or two hands with
   and without objects, random backgrounds, the Kinect noise model
   (:func:`torchhand.salient.training_data.render_salient_frames`); for colour, shaded
   renders seen by a ring of cameras, with Ballan's structural noise on a share
   ``circles`` of the frames. The validation frames are
   whole held-out thesis sequences (split by sequence) plus random poses of another seed.
2. Trains with AdamW and a one-cycle schedule on random crops (scale and flip
   augmentation; colour also brightness, contrast, white balance and pixel noise),
   checkpointing every ``checkpoint_every`` steps. ``--resume``
   continues exactly where the last checkpoint stopped (model, optimizer, scheduler,
   RNG states, step); it refuses a config that differs from the run's ``config.json``.
3. Writes ``RUN/salient_fingertips.pt`` (colour: ``RUN/salient_nails_rgb.pt``) and its
   ``.onnx``, ``RUN/log.jsonl`` and
   ``RUN/done.json``. A finished or started run is never overwritten without ``--force``.

``--config`` is a JSON object overriding fields of :class:`TrainConfig`.

Distributed data-parallel training (DDP, ``docs/salient.md``)::

    torchrun --nproc_per_node 2 -m train.salient_detector --out runs/salient [--resume]

runs one process per rank (gloo on CPU, nccl with SyncBatchNorm on CUDA, one GPU per
rank). The global batch stays ``batch_size``: every rank draws the same batch (one
generator, seeded alike) and crops only its own ``batch_size / world`` samples of it
(:func:`sample_batch` ``part``), and the loss is normalised by the positives of the
whole batch, so a step sees the data of the single-process step. Rank 0 renders the
frames, writes the log, the checkpoints and the results; a resume is exact for the
same world size.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from tqdm import tqdm

from torchhand.salient.training_data import (SalientFrames, concat_frames, load_frames, render_salient_frames,
                                             save_frames, visible_mm2)
from torchhand.salient.detector import SalientConfig, SalientNet, export_onnx
from torchhand.salient.hough import DEFAULT_MAX_DETECTIONS, DEFAULT_THRESHOLD, STRIDE, detect_peaks
from torchhand.salient.precision_recall import average_precision

REPO = Path(__file__).resolve().parents[1]
DEFAULT_HIA_ROOT = REPO.parent / "shared" / "data" / "hands_in_action"
FOCAL_PX = 525.0  # the thesis camera; positive radius in px = radius_mm * f / z


#: Version of the rendered frames: caches of another version are rendered again
#: (2: the visible fingertip area counts only pixels with a sensor measurement;
#: 3: colour frames).
DATA_VERSION = 3
#: Weight file name of a run, per modality.
WEIGHT_NAMES = {"depth": "salient_fingertips", "colour": "salient_nails_rgb"}


@dataclass
class TrainConfig:
    """Everything that determines a training run (``--config`` JSON overrides fields)."""

    seed: int = 0
    modality: str = "depth"  # "depth" (fingertips) or "colour" (nails); sets the network's too
    # --- data (a change re-renders; cached under a hash of these fields)
    train_sequences: List[str] = field(default_factory=lambda: [
        "01", "02", "04", "06", "08", "09", "11", "12", "13", "15", "16", "17", "19"])
    val_sequences: List[str] = field(default_factory=lambda: ["03", "10", "20"])
    sequence_frames: int = 40  # frames per training sequence, evenly spaced
    val_sequence_frames: int = 30
    random_scenes: List[List[str]] = field(default_factory=lambda: [
        ["hand_right"], ["hand_left"], ["hand_right", "hand_left"], ["hand_right", "ball"],
        ["hand_left", "cube"], ["hand_right", "hand_left", "ball"]])
    random_frames: int = 90  # per random scene
    val_random_frames: int = 60  # one two-hand scene, another seed
    random_distance_mm: List[float] = field(default_factory=lambda: [350.0, 850.0])
    data_seed: int = 1
    val_seed: int = 1001
    background_spheres: int = 0  # distractor spheres per training background (at most)
    circles: float = 0.5  # colour: share of the frames with Ballan's structural noise
    # --- network
    network: dict = field(default_factory=dict)  # SalientConfig fields
    # --- optimisation
    steps: int = 2500
    batch_size: int = 16
    crop: int = 160
    scale_range: List[float] = field(default_factory=lambda: [0.8, 1.25])
    p_crop_on_tip: float = 0.8
    lr: float = 4e-3
    weight_decay: float = 1e-4
    positive_radius_mm: float = 8.0
    positive_depth_mm: float = 30.0
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    offset_weight: float = 0.1
    colour_jitter: float = 0.25  # colour: brightness/contrast range (+-), a fifth of it per channel
    pixel_noise: float = 6.0  # colour: at most this std of Gaussian pixel noise (0..255)
    checkpoint_every: int = 250
    threads: int = 2
    # --- fine-tuning: start from these weights (a SalientNet.save file) instead of random
    init_weights: str = ""

    def data_key(self) -> str:
        d = {"version": DATA_VERSION}
        d.update({k: getattr(self, k) for k in ("train_sequences", "val_sequences", "sequence_frames",
                                           "val_sequence_frames", "random_scenes", "random_frames",
                                           "val_random_frames", "random_distance_mm", "data_seed", "val_seed",
                                           "background_spheres", "modality")})
        if self.modality == "colour":
            d["circles"] = self.circles
        return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


def load_config(path: Optional[Path]) -> TrainConfig:
    """Defaults overridden by the JSON object in ``path``; unknown fields are an error."""
    cfg = TrainConfig()
    if path is None:
        return cfg
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"{path}: cannot read the config ({e})")
    if not isinstance(data, dict):
        raise SystemExit(f"{path}: the config must be a JSON object of TrainConfig fields")
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SystemExit(f"{path}: unknown config field(s) {unknown}; known fields: {sorted(known)}")
    cfg = dataclasses.replace(cfg, **data)
    if cfg.modality not in WEIGHT_NAMES:
        raise SystemExit(f"{path}: field 'modality' must be one of {sorted(WEIGHT_NAMES)}, got {cfg.modality!r}")
    if cfg.network.get("modality", cfg.modality) != cfg.modality:
        raise SystemExit(f"{path}: network.modality {cfg.network['modality']!r} differs from modality {cfg.modality!r}")
    try:
        net_config(cfg)
    except (TypeError, ValueError) as e:
        raise SystemExit(f"{path}: field 'network': {e}")
    return cfg


def net_config(cfg: TrainConfig) -> SalientConfig:
    """The network of a run: ``cfg.network`` with the run's modality."""
    return SalientConfig(**{**cfg.network, "modality": cfg.modality})


# ----------------------------------------------------------------------------- data


def _sequence_frames(hia_root: Path, seq: str, n: int, seed: int, spheres: int = 0, **kw) -> SalientFrames:
    from torchhand.data.synth import thesis_motion
    from torchhand.io.thesis import sequence_models

    _, bounds = sequence_models(hia_root, seq)
    step = max(1, bounds.total_aligned // n)
    frames = thesis_motion(hia_root, seq, frames=slice(0, step * n, step), dtype=torch.float32)
    return render_salient_frames(frames, seed=seed, progress=False, spheres=spheres, **kw)


def _random_frames(scene: List[str], n: int, seed: int, distance, spheres: int = 0, **kw) -> SalientFrames:
    from torchhand.data.synth import random_poses

    frames = random_poses(scene, n, seed=seed, distance=tuple(distance), dtype=torch.float32)
    return render_salient_frames(frames, seed=seed, progress=False, spheres=spheres, **kw)


def build_datasets(cfg: TrainConfig, hia_root: Path, cache: Path) -> tuple:
    """(train, val) :class:`SalientFrames`, rendered once and cached under ``cache/<key>``."""
    d = cache / cfg.data_key()
    train_f, val_f = d / "train.npz", d / "val.npz"
    if train_f.is_file() and val_f.is_file():
        print(f"reusing rendered frames from {d}")
        return load_frames(train_f), load_frames(val_f)
    overlap = sorted(set(cfg.train_sequences) & set(cfg.val_sequences))
    if overlap:
        raise SystemExit(f"config: sequences {overlap} are in both train_sequences and val_sequences")
    d.mkdir(parents=True, exist_ok=True)
    jobs = [("seq", s, cfg.sequence_frames, cfg.data_seed + k) for k, s in enumerate(cfg.train_sequences)]
    jobs += [("rand", sc, cfg.random_frames, cfg.data_seed + 100 + k) for k, sc in enumerate(cfg.random_scenes)]
    val_jobs = [("seq", s, cfg.val_sequence_frames, cfg.val_seed + k) for k, s in enumerate(cfg.val_sequences)]
    val_jobs += [("rand", ["hand_right", "hand_left"], cfg.val_random_frames, cfg.val_seed + 100)]
    out = {}
    for split, js in (("train", jobs), ("val", val_jobs)):
        parts = []
        spheres = cfg.background_spheres if split == "train" else 0  # validation as evaluated
        kw = {"modality": cfg.modality, "circles": cfg.circles} if cfg.modality == "colour" else {}
        for kind, what, n, seed in tqdm(js, desc=f"render {split}", unit="set"):
            if kind == "seq":
                parts.append(_sequence_frames(hia_root, what, n, seed, spheres, **kw))
            else:
                parts.append(_random_frames(what, n, seed, cfg.random_distance_mm, spheres, **kw))
        out[split] = concat_frames(parts)
        tmp = d / f"{split}.tmp.npz"
        save_frames(out[split], tmp)
        tmp.rename(d / f"{split}.npz")  # atomic: a crash never leaves a half-written cache file
    (d / "data_config.json").write_text(json.dumps(asdict(cfg), indent=2))
    return out["train"], out["val"]


# ------------------------------------------------------------------------- batches


def sample_batch(data: SalientFrames, cfg: TrainConfig, g: torch.Generator, part: tuple = (0, 1)) -> tuple:
    """Random crops with scale and flip augmentation.

    ``part = (rank, world)``: the random draws are those of the whole batch
    (``cfg.batch_size``, the same on every rank), the crops only those of the rank's
    contiguous share (the distributed sampler of DDP training).

    Returns (image (B, 1, C, C) depth mm, or (B, 3, C, C) RGB 0..255, tips (B, P, 3)
    [u, v, z] in crop pixels (NaN = none), visible (B, P) bool, ignore (B, P) bool
    (barely visible fingertips)), B = ``batch_size / world``.
    """
    colour = data.image.ndim == 4
    N, H, W = data.image.shape[:3]
    B, C = cfg.batch_size, cfg.crop
    P = data.uv.shape[1]
    vis_mm2 = visible_mm2(data)
    idx = torch.randint(0, N, (B,), generator=g).numpy()
    lo, hi = cfg.scale_range
    scale = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * torch.rand(B, generator=g)).numpy()
    on_tip = (torch.rand(B, generator=g) < cfg.p_crop_on_tip).numpy()
    pick = torch.rand(B, 2, generator=g).numpy()
    flip = (torch.rand(B, generator=g) < 0.5).numpy()
    if colour:  # photometric draws: contrast, brightness, per-channel gain, noise std
        j = cfg.colour_jitter
        contrast = (1 + j * (2 * torch.rand(B, generator=g) - 1)).numpy()
        bright = (j * 127.5 * (2 * torch.rand(B, generator=g) - 1)).numpy()
        gain = (1 + 0.2 * j * (2 * torch.rand(B, 3, generator=g) - 1)).numpy()
        sigma = (cfg.pixel_noise * torch.rand(B, generator=g)).numpy()
        noise_seed = torch.randint(0, 2 ** 31, (B,), generator=g).numpy()
    rank, world = part
    share = range(rank * B // world, (rank + 1) * B // world)
    image = np.zeros((len(share), 3 if colour else 1, C, C), np.float32)
    tips = np.full((len(share), P, 3), np.nan, np.float32)
    for i, b in enumerate(share):
        f, s = idx[b], scale[b]
        size = int(round(C / s))  # source window, resized to C x C
        vis = np.nonzero(data.area_mm2[f] >= vis_mm2)[0]
        if on_tip[b] and len(vis):
            t = vis[int(pick[b, 0] * len(vis)) % len(vis)]
            cu, cv = data.uv[f, t]
            c0 = int(cu - size * (0.15 + 0.7 * pick[b, 1]))
            r0 = int(cv - size * (0.15 + 0.7 * (1 - pick[b, 1])))
        else:
            c0 = int(pick[b, 0] * (W - size))
            r0 = int(pick[b, 1] * (H - size))
        c0 = min(max(c0, 0), W - size)
        r0 = min(max(r0, 0), H - size)
        win = data.image[f, r0: r0 + size, c0: c0 + size].astype(np.float32)
        # Nearest-neighbour resize (no mixing of depths across edges); zooming in by s
        # is the same as moving the scene s times closer, so depth is divided by s.
        src = np.minimum((np.arange(C) / s).astype(np.int64), size - 1)
        win = win[src][:, src]
        uv = (data.uv[f] - np.array([c0, r0], np.float32) + 0.5) * s - 0.5
        if flip[b]:
            win = win[:, ::-1]
            uv[:, 0] = C - 1 - uv[:, 0]
        if colour:
            win = (win - 127.5) * contrast[b] + 127.5 + bright[b]
            win = win * gain[b] + np.random.default_rng(noise_seed[b]).normal(0.0, sigma[b], win.shape)
            image[i] = np.clip(win, 0, 255).transpose(2, 0, 1)
        else:
            image[i, 0] = win / s
        tips[i, :, :2] = uv
        tips[i, :, 2] = data.tip_depth[f] / s
    area = data.area_mm2[idx[share.start : share.stop]]
    visible = area >= vis_mm2
    ignore = (area > 0) & ~visible
    return (torch.from_numpy(image), torch.from_numpy(tips), torch.from_numpy(visible), torch.from_numpy(ignore))


def targets(image: torch.Tensor, tips: torch.Tensor, visible: torch.Tensor, ignore: torch.Tensor,
            cfg: TrainConfig) -> tuple:
    """Per-cell labels: positive (B, h, w), loss weight (B, h, w), offset target (B, 2, h, w).

    A cell is positive if its centre is within ``positive_radius_mm * f / z`` px of a
    visible fingertip centre and (depth input only) its depth within
    ``positive_depth_mm`` of the tip's; cells near barely visible fingertips get no
    classification loss.
    """
    B, channels, Hc, Wc = image.shape
    h, w = Hc // STRIDE, Wc // STRIDE
    ys = torch.arange(h, dtype=torch.float32) * STRIDE + 1.5
    xs = torch.arange(w, dtype=torch.float32) * STRIDE + 1.5
    cells = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(1, h * w, 1, 2)
    uv = torch.nan_to_num(tips[..., :2], nan=-1e4)
    z = torch.nan_to_num(tips[..., 2], nan=1e4)
    dist = (cells - uv[:, None]).norm(dim=-1)  # (B, hw, P)
    radius = (cfg.positive_radius_mm * FOCAL_PX / z.clamp_min(100.0))[:, None]  # (B, 1, P)
    near_z = torch.ones_like(dist, dtype=torch.bool)
    if channels == 1:  # depth: the cell must lie on the fingertip, not on what is behind it
        cell_depth = image[:, 0, 1::STRIDE, 1::STRIDE].reshape(B, h * w, 1)
        near_z = (cell_depth - z[:, None]).abs() <= cfg.positive_depth_mm
    pos_tip = (dist <= radius) & near_z & visible[:, None]
    dist_pos = torch.where(pos_tip, dist, torch.full_like(dist, float("inf")))
    nearest = dist_pos.argmin(-1)  # (B, hw)
    positive = pos_tip.any(-1)
    ign = ((dist <= 1.5 * radius) & ignore[:, None]).any(-1) & ~positive
    target_uv = torch.gather(uv, 1, nearest[..., None].expand(B, h * w, 2))
    offset = (target_uv - cells[:, :, 0]).permute(0, 2, 1).reshape(B, 2, h, w)
    return positive.reshape(B, h, w), (~ign).float().reshape(B, h, w), offset


def loss_fn(out, positive, weight, offset, cfg: TrainConfig, npos: Optional[torch.Tensor] = None) -> tuple:
    """Focal loss on the scores (normalised by the positives, ``npos``: of the whole
    batch where it is split over ranks) + smooth-L1 on offsets."""
    logits = out.logits[:, 0]
    p = torch.sigmoid(logits)
    y = positive.float()
    ce = F.binary_cross_entropy_with_logits(logits, y, reduction="none")
    pt = p * y + (1 - p) * (1 - y)
    alpha = cfg.focal_alpha * y + (1 - cfg.focal_alpha) * (1 - y)
    npos = (y.sum() if npos is None else npos).clamp_min(1.0)
    cls = (alpha * (1 - pt) ** cfg.focal_gamma * ce * weight).sum() / npos
    reg = F.smooth_l1_loss(out.offsets, offset, reduction="none", beta=1.0).sum(1)
    reg = (reg * y).sum() / npos
    return cls + cfg.offset_weight * reg, cls.detach(), reg.detach()


# ---------------------------------------------------------------------- validation


def evaluate_ap(net: SalientNet, data: SalientFrames, threshold: float = DEFAULT_THRESHOLD, batch: int = 8) -> float:
    """VOC AP (10 px) of ``net`` on full frames of ``data``, with the detector's peak
    picking defaults (as ``eval/eval_salient.py`` measures it)."""
    was_training = net.training
    net.eval()
    dets_uv, dets_s, gts, igns = [], [], [], []
    vis_mm2 = visible_mm2(data)
    with torch.no_grad():
        for s in range(0, len(data.image), batch):
            x = torch.from_numpy(data.image[s: s + batch].astype(np.float32))
            x = x.permute(0, 3, 1, 2) if x.ndim == 4 else x[:, None]
            out = net(x.to(next(net.parameters()).device))
            for b, d in enumerate(detect_peaks(out.hough, threshold=threshold, max_detections=DEFAULT_MAX_DETECTIONS,
                                               logits=out.logits)):
                f = s + b
                dets_uv.append(d.uv.cpu().numpy())
                dets_s.append(d.score.cpu().numpy())
                a = data.area_mm2[f]
                gts.append(data.uv[f][a >= vis_mm2])
                igns.append(data.uv[f][(a > 0) & (a < vis_mm2)])
    net.train(was_training)
    return average_precision(dets_uv, dets_s, gts, radius=10.0, gt_ignore=igns).ap


# ------------------------------------------------------------------------ the run


def _rng_state(g: torch.Generator) -> dict:
    return {"sampler": g.get_state(), "torch": torch.get_rng_state(), "numpy": np.random.get_state()[1]}


def world() -> tuple:
    """(rank, world size, device) of this process: a torchrun rank joins the process
    group here (gloo on CPU, nccl on CUDA: one GPU per local rank); a plain run is
    (0, 1, cpu)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return 0, 1, torch.device("cpu")
    cuda = torch.cuda.is_available()
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    device = torch.device("cpu")
    if cuda:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return dist.get_rank(), dist.get_world_size(), device


def _barrier(size: int) -> None:
    if size > 1:
        dist.barrier()


def train(cfg: TrainConfig, out: Path, train_data: SalientFrames, val_data: SalientFrames,
          resume: bool, progress: bool = True, stop_at: Optional[int] = None) -> SalientNet:
    """Train (or continue from ``out/checkpoint.pt`` if ``resume``) up to ``cfg.steps``,
    on every rank of a torchrun job (see the module).

    ``stop_at`` ends the call after that step, once its checkpoint is written (an
    interruption: a job's time limit, or the resume test).
    """
    rank, size, device = world()
    if cfg.batch_size % size:
        raise SystemExit(f"batch_size {cfg.batch_size} is not a multiple of the {size} ranks")
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    net = SalientNet(net_config(cfg))
    if cfg.init_weights:
        start = SalientNet.load(cfg.init_weights)
        if start.config != net.config:
            raise SystemExit(f"{cfg.init_weights}: network {start.config} differs from the config's {net.config}")
        net.load_state_dict(start.state_dict())
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=cfg.steps, pct_start=0.1)
    step = 0
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.is_file():
        state = torch.load(ckpt, weights_only=False, map_location="cpu")
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        g.set_state(state["rng"]["sampler"])
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(("MT19937", state["rng"]["numpy"], 624, 0, 0.0))
        step = state["step"]
        was = state.get("world_size", 1)
        if rank == 0:
            print(f"resuming {out} at step {step}" + ("" if was == size else
                  f" (checkpointed by {was} ranks, resumed by {size}: not an exact continuation)"))
    net.to(device)
    model = net
    if size > 1:
        from torch.nn.parallel import DistributedDataParallel

        if device.type == "cuda":
            net = torch.nn.SyncBatchNorm.convert_sync_batchnorm(net)
        model = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None)
    model.train()
    log = (out / "log.jsonl").open("a") if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=step, desc="train salient", unit="step", disable=not progress or rank != 0)
    t0 = time.perf_counter()
    while step < cfg.steps:
        image, tips, visible, ignore = sample_batch(train_data, cfg, g, (rank, size))
        positive, weight, offset = targets(image, tips, visible, ignore, cfg)
        positive, weight, offset, image = (x.to(device) for x in (positive, weight, offset, image))
        npos = positive.float().sum()
        if size > 1:  # normalised by the whole batch; DDP averages the ranks' gradients, hence x size
            dist.all_reduce(npos)
        loss, cls, reg = loss_fn(model(image), positive, weight, offset, cfg, npos)
        opt.zero_grad(set_to_none=True)
        (loss * size).backward()
        opt.step()
        sched.step()
        step += 1
        parts = torch.stack([loss.detach(), cls, reg])
        if size > 1:  # the whole batch's loss: the sum of the ranks' shares
            dist.all_reduce(parts)
        loss_v, cls_v, reg_v = parts.tolist()
        bar.update(1)
        bar.set_postfix(loss=f"{loss_v:.3f}", cls=f"{cls_v:.3f}", off=f"{reg_v:.2f}")
        if step % cfg.checkpoint_every == 0 or step == cfg.steps or step == stop_at:
            if rank == 0:
                rec = {"step": step, "loss": loss_v, "cls": cls_v, "offset": reg_v, "lr": sched.get_last_lr()[0],
                       "seconds": time.perf_counter() - t0, "world_size": size}
                if step % (4 * cfg.checkpoint_every) == 0 or step == cfg.steps:
                    rec["val_ap"] = evaluate_ap(net, val_data)
                log.write(json.dumps(rec) + "\n")
                log.flush()
                tmp = out / "checkpoint.tmp.pt"
                torch.save({"model": {k: v.cpu() for k, v in net.state_dict().items()},
                            "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "rng": _rng_state(g),
                            "step": step, "config": asdict(cfg), "world_size": size}, tmp)
                tmp.replace(ckpt)  # atomic
            _barrier(size)
        if stop_at is not None and step >= stop_at:
            break
    bar.close()
    if log is not None:
        log.close()
    plain = SalientNet(net_config(cfg))
    plain.load_state_dict({k: v.cpu() for k, v in net.state_dict().items()})  # SyncBatchNorm: same keys
    return plain.eval()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="run folder")
    ap.add_argument("--config", type=Path, help="JSON object overriding TrainConfig fields")
    ap.add_argument("--cache", type=Path, help="rendered-frame cache (default: RUN/cache)")
    ap.add_argument("--hia-root", type=Path, default=DEFAULT_HIA_ROOT, help="thesis data root")
    ap.add_argument("--force", action="store_true", help="replace an existing run")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    ap.add_argument("--stop-at", type=int, help="end after this step, checkpointed (a job's time limit); "
                    "--resume continues")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    out: Path = args.out
    cfg_file = out / "config.json"
    # every rank checks alike (so all stop on the same error); only rank 0 writes
    if args.resume and args.force:
        raise SystemExit("--resume and --force exclude each other")
    if args.resume:
        if not cfg_file.is_file():
            raise SystemExit(f"{out}: nothing to resume ({cfg_file} not found)")
        saved = json.loads(cfg_file.read_text())
        mine = json.loads(json.dumps(asdict(cfg)))
        diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
        if diff:
            src = args.config if args.config is not None else "the defaults (no --config)"
            raise SystemExit(f"cannot resume {out}: config field(s) {diff} of {src} differ from {cfg_file} "
                             f"(e.g. {diff[0]}: {mine.get(diff[0])!r} vs {saved.get(diff[0])!r}); "
                             "pass the run's config or start a new run")
        if (out / "done.json").is_file():
            print(f"{out} is already finished; nothing to do")
            return 0
    elif out.exists() and any(out.iterdir()) and not args.force:
        what = "a finished run" if (out / "done.json").is_file() else "not empty"
        raise SystemExit(f"{out} is {what}; pass --force to replace it or --resume to continue it")
    rank, size, _ = world()
    if rank == 0:
        if not args.resume and out.exists() and any(out.iterdir()):
            keep_cache = args.cache is None and (out / "cache").is_dir()
            for p in out.iterdir():  # keep the render cache, it does not depend on the run
                if keep_cache and p.name == "cache":
                    continue
                shutil.rmtree(p) if p.is_dir() else p.unlink()
        out.mkdir(parents=True, exist_ok=True)
        if not args.resume:
            cfg_file.write_text(json.dumps(asdict(cfg), indent=2))
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()
    if rank == 0:  # rank 0 renders (or finds) the frames, the others read its cache
        train_data, val_data = build_datasets(cfg, args.hia_root, args.cache or out / "cache")
    _barrier(size)
    if rank != 0:
        train_data, val_data = build_datasets(cfg, args.hia_root, args.cache or out / "cache")
    t_data = time.perf_counter() - t_start
    if rank == 0:
        print(f"frames: {len(train_data.image)} train, {len(val_data.image)} val ({t_data:.0f} s)"
              + (f"; {size} ranks of {cfg.batch_size // size} crops each" if size > 1 else ""))
    net = train(cfg, out, train_data, val_data, args.resume, progress=not args.no_progress, stop_at=args.stop_at)
    if args.stop_at is not None and args.stop_at < cfg.steps:
        if rank == 0:
            print(f"stopped after step {args.stop_at} of {cfg.steps}; --resume continues")
        return 0
    t_total = time.perf_counter() - t_start
    if rank == 0:
        name = WEIGHT_NAMES[cfg.modality]
        net.save(out / f"{name}.pt")
        export_onnx(net, out / f"{name}.onnx")
        val_ap = evaluate_ap(net, val_data)
        done = {"steps": cfg.steps, "val_ap": val_ap, "seconds_data": t_data, "seconds_total": t_total,
                "train_frames": int(len(train_data.image)), "val_frames": int(len(val_data.image)),
                "world_size": size}
        (out / "done.json").write_text(json.dumps(done, indent=2))
        print(json.dumps(done, indent=2))
    _barrier(size)
    return 0


if __name__ == "__main__":
    code = main()
    if dist.is_initialized():
        dist.destroy_process_group()
    sys.exit(code)
