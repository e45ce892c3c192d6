"""Map-style torch Datasets over sequences in the torchhand layout.

One item is one frame of one sequence::

    ds = SequenceDataset("data/hia_16")                 # or MultiSequenceDataset([...])
    loader = DataLoader(ds, batch_size=8, num_workers=2, collate_fn=collate_frames)
    for batch in loader:
        batch.depth          # (B, C, H, W) float32 mm, 0 = missing
        batch.K, batch.T_cw  # (B, C, 3, 3), (B, C, 4, 4)
        batch.theta          # (B, D) ground truth, or None without gt/

Items are :class:`Frame` records. ``collate_frames`` stacks tensors; fields whose
sizes differ across the batch (theta of scenes with different DoF counts,
keypoints of different models) are returned as lists instead of stacked tensors.
Workers open files lazily, so datasets pickle cheaply into worker processes.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import List, Optional, Sequence, Union

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset

from torchhand.data.layout import (SequenceError, SequenceLayout, read_depth, read_poses, read_rgb,
                                   read_sequence_info)

__all__ = ["Frame", "SequenceDataset", "MultiSequenceDataset", "collate_frames"]


@dataclass
class Frame:
    """One frame (or, after collate, a batch of frames; then every tensor gains a
    leading batch dimension B and str/int fields become lists).

    depth: (C, H, W) float32 mm; rgb: (C, H, W, 3) uint8 or None; K: (C, 3, 3);
    T_cw: (C, 4, 4); theta: (D,) or None; keypoints_3d: (C, P, 3) mm or None;
    keypoints_2d: (C, P, 2) px or None; model_ids: (H, W) int64 (camera 0; -1
    background) or None; sequence: name; index: frame number.
    """

    depth: torch.Tensor
    K: torch.Tensor
    T_cw: torch.Tensor
    sequence: Union[str, List[str]]
    index: Union[int, torch.Tensor]
    rgb: Optional[torch.Tensor] = None
    theta: Optional[torch.Tensor] = None
    keypoints_3d: Optional[torch.Tensor] = None
    keypoints_2d: Optional[torch.Tensor] = None
    model_ids: Optional[torch.Tensor] = None


class SequenceDataset(Dataset):
    """Frames of one sequence folder.

    Args:
        root: the sequence folder (with sequence.json).
        rgb: load colour images when the sequence has them.
        ground_truth: load ``gt/`` when present ("auto"), always (True: error if
            missing) or never (False, e.g. for a tracker).
        frames: optional subset of frame numbers.
    """

    def __init__(self, root, rgb: bool = False, ground_truth: Union[bool, str] = "auto",
                 frames: Optional[Sequence[int]] = None):
        self.root = Path(root)
        self.layout = SequenceLayout(self.root)
        self.info = read_sequence_info(self.root)
        self.rgb = rgb and self.info.has_rgb
        gt = self.layout.gt
        if ground_truth is True and not gt.meta.is_file():
            raise SequenceError(f"{gt.root}: no ground truth in this sequence")
        self.with_gt = ground_truth is True or (ground_truth == "auto" and gt.meta.is_file())
        self.frames = list(range(self.info.frames)) if frames is None else list(frames)
        bad = [k for k in self.frames if not 0 <= k < self.info.frames]
        if bad:
            raise IndexError(f"{self.root}: frames {bad[:5]} outside 0..{self.info.frames - 1}")
        self.K = torch.stack([c.K.float() for c in self.info.cameras])
        self.T_cw = torch.stack([c.T_cw.float() for c in self.info.cameras])
        self._gt = None  # loaded lazily, once per worker

    def __len__(self) -> int:
        return len(self.frames)

    def _ground_truth(self):
        if self._gt is None:
            poses = read_poses(self.layout.gt)
            if len(poses.theta) != self.info.frames:
                raise SequenceError(f"{self.layout.gt.root}: {len(poses.theta)} frames of ground truth, "
                                    f"sequence.json says {self.info.frames}")
            self._gt = poses
        return self._gt

    def __getitem__(self, i: int) -> Frame:
        k = self.frames[i]
        C = len(self.info.cameras)
        depth = np.stack([read_depth(self.layout.depth(k, c), self.info.depth_unit_mm)
                          for c in range(C)])
        frame = Frame(depth=torch.from_numpy(depth), K=self.K, T_cw=self.T_cw, sequence=self.info.name, index=k)
        if self.rgb:
            frame.rgb = torch.from_numpy(np.stack([read_rgb(self.layout.rgb(k, c))
                                                   for c in range(C)]))
        if self.with_gt:
            gt = self._ground_truth()
            frame.theta = torch.from_numpy(gt.theta[k]).float()
            frame.keypoints_3d = torch.from_numpy(gt.keypoints_3d[k]).float()
            frame.keypoints_2d = torch.from_numpy(gt.keypoints_2d[k]).float()
            ids_path = self.layout.gt.ids(k)
            if ids_path.is_file():
                import cv2

                ids = cv2.imread(str(ids_path), cv2.IMREAD_UNCHANGED)
                frame.model_ids = torch.from_numpy(ids.astype(np.int64) - 1)
        return frame


class MultiSequenceDataset(ConcatDataset):
    """Frames of several sequences, indexed one after the other."""

    def __init__(self, roots: Sequence, **kwargs):
        if not roots:
            raise ValueError("MultiSequenceDataset needs at least one sequence folder")
        super().__init__([SequenceDataset(r, **kwargs) for r in roots])


def collate_frames(frames: List[Frame]) -> Frame:
    """Batch :class:`Frame` items: stack equal-shaped tensors, list the rest."""
    out = {}
    for f in fields(Frame):
        vals = [getattr(fr, f.name) for fr in frames]
        if all(v is None for v in vals):
            out[f.name] = None
        elif all(isinstance(v, torch.Tensor) for v in vals) and len({tuple(v.shape) for v in vals}) == 1:
            out[f.name] = torch.stack(vals)
        elif f.name == "index":
            out[f.name] = torch.as_tensor(vals)
        else:
            out[f.name] = vals
    return Frame(**out)
