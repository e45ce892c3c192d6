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

import hashlib
import json
import math
import sys
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
from train import trainer
from train.trainer import RunConfig

FOCAL_PX = 525.0  # the thesis camera; positive radius in px = radius_mm * f / z


#: Version of the rendered frames: caches of another version are rendered again
#: (2: the visible fingertip area counts only pixels with a sensor measurement;
#: 3: colour frames).
DATA_VERSION = 3
#: Weight file name of a run, per modality.
WEIGHT_NAMES = {"depth": "salient_fingertips", "colour": "salient_nails_rgb"}


@dataclass
class TrainConfig(RunConfig):
    """Everything that determines a training run (``--config`` JSON overrides fields):
    the fields of every run (:class:`train.trainer.RunConfig`: seed, steps, batch_size,
    lr, weight_decay, checkpoint_every, threads, init_weights) and these."""

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
    crop: int = 160
    scale_range: List[float] = field(default_factory=lambda: [0.8, 1.25])
    p_crop_on_tip: float = 0.8
    positive_radius_mm: float = 8.0
    positive_depth_mm: float = 30.0
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    offset_weight: float = 0.1
    colour_jitter: float = 0.25  # colour: brightness/contrast range (+-), a fifth of it per channel
    pixel_noise: float = 6.0  # colour: at most this std of Gaussian pixel noise (0..255)

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
    """Defaults overridden by the JSON object in ``path``; unknown fields are an error,
    and so are a modality or network the detector does not have."""
    return trainer.checked_config(SalientTask, path)


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


class SalientTask(trainer.Task):
    """The salient point detector as a task of the training loop (:mod:`train.trainer`)."""

    name = "salient"
    config_type = TrainConfig
    sample = "crops"

    def check_config(self, cfg: TrainConfig) -> None:
        if cfg.modality not in WEIGHT_NAMES:
            raise ValueError(f"field 'modality' must be one of {sorted(WEIGHT_NAMES)}, got {cfg.modality!r}")
        if cfg.network.get("modality", cfg.modality) != cfg.modality:
            raise ValueError(f"network.modality {cfg.network['modality']!r} differs from modality {cfg.modality!r}")
        try:
            net_config(cfg)
        except (TypeError, ValueError) as e:
            raise ValueError(f"field 'network': {e}")

    def build_net(self) -> SalientNet:
        return SalientNet(net_config(self.cfg))

    def datasets(self, hia_root: Path, cache: Path) -> tuple:
        return build_datasets(self.cfg, hia_root, cache)

    def batch(self, data: SalientFrames, g: torch.Generator, part: tuple) -> tuple:
        """(image (B, 1|3, C, C), positive (B, h, w), weight (B, h, w), offset (B, 2, h, w)):
        :func:`sample_batch` and its :func:`targets`."""
        image, tips, visible, ignore = sample_batch(data, self.cfg, g, part)
        return (image, *targets(image, tips, visible, ignore, self.cfg))

    def loss(self, model, batch: tuple, device: torch.device, size: int) -> tuple:
        image, positive, weight, offset = (x.to(device) for x in batch)
        npos = positive.float().sum()
        if size > 1:  # normalised by the positives of the whole batch
            dist.all_reduce(npos)
        loss, cls, reg = loss_fn(model(image), positive, weight, offset, self.cfg, npos)
        return loss, {"loss": loss.detach(), "cls": cls, "offset": reg}

    def validate(self, net: SalientNet, val: SalientFrames) -> dict:
        return {"val_ap": evaluate_ap(net, val)}

    def finish(self, net: SalientNet, out: Path, val: SalientFrames) -> dict:
        name = WEIGHT_NAMES[self.cfg.modality]
        net.save(out / f"{name}.pt")
        export_onnx(net, out / f"{name}.onnx")
        return {"val_ap": evaluate_ap(net, val)}

    def describe_data(self, train: SalientFrames, val: SalientFrames) -> str:
        return f"frames: {len(train.image)} train, {len(val.image)} val"

    def data_fields(self, train: SalientFrames, val: SalientFrames) -> dict:
        return {"train_frames": int(len(train.image)), "val_frames": int(len(val.image))}


def train(cfg: TrainConfig, out: Path, train_data: SalientFrames, val_data: SalientFrames,
          resume: bool, progress: bool = True, stop_at: Optional[int] = None) -> SalientNet:
    """:func:`train.trainer.train` of the salient task with config ``cfg``."""
    return trainer.train(SalientTask(cfg), out, train_data, val_data, resume, progress=progress, stop_at=stop_at)


def main(argv=None) -> int:
    return trainer.main(SalientTask, argv, __doc__)


if __name__ == "__main__":
    code = main()
    if dist.is_initialized():
        dist.destroy_process_group()
    sys.exit(code)
