"""torch Datasets over sequence folders: Frame fields, ground truth on/off, DataLoader
workers, mixed scenes in one batch, and missing files."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from torchhand.data.torch_datasets import Frame, MultiSequenceDataset, SequenceDataset, collate_frames
from torchhand.data.layout import SequenceError, frame_name, read_depth, read_poses
from torchhand.data.synth import random_poses, write_synthetic_sequence

H, W = 480, 640


@pytest.fixture(scope="module")
def seqs(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    a = write_synthetic_sequence(random_poses(["hand_right"], 4, seed=0), root / "a", noise="none", progress=False)
    b = write_synthetic_sequence(random_poses(["hand_right", "ball"], 2, seed=1), root / "b", noise="none",
                                 progress=False)
    return a, b


@pytest.fixture
def seq_copy(seqs, tmp_path):
    """A private copy of the 4-frame sequence that a test may damage."""
    return shutil.copytree(seqs[0], tmp_path / "a")


def test_len_and_frame_fields(seqs):
    a, _ = seqs
    ds = SequenceDataset(a)
    assert len(ds) == 4
    gt = read_poses(a / "gt")
    for i in (0, 3):
        f = ds[i]
        assert isinstance(f, Frame)
        assert f.index == i and f.sequence == "random_0"
        assert f.depth.shape == (1, H, W) and f.depth.dtype == torch.float32
        np.testing.assert_array_equal(f.depth[0].numpy(), read_depth(a / "depth" / frame_name(i)))
        assert f.K.shape == (1, 3, 3) and f.T_cw.shape == (1, 4, 4)
        assert f.K[0, 0, 0] == 525.0 and torch.equal(f.T_cw[0], torch.eye(4))
        assert f.rgb is None  # rgb=False by default
        assert f.theta.shape == (37,) and f.theta.dtype == torch.float32
        assert f.keypoints_3d.shape == (1, 21, 3) and f.keypoints_2d.shape == (1, 21, 2)
        np.testing.assert_allclose(f.theta.numpy(), gt.theta[i], rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(f.keypoints_2d.numpy(), gt.keypoints_2d[i], rtol=1e-6, atol=1e-4)
        assert f.model_ids.shape == (H, W) and f.model_ids.dtype == torch.int64
        assert set(f.model_ids.unique().tolist()) == {-1, 0}
        assert torch.equal(f.model_ids >= 0, f.depth[0] > 0)  # noise none: depth exactly where the hand is


def test_rgb_frames(seqs):
    ds = SequenceDataset(seqs[0], rgb=True)
    f = ds[1]
    assert f.rgb.shape == (1, H, W, 3) and f.rgb.dtype == torch.uint8
    assert (f.rgb[0][f.model_ids < 0] == 64).all()  # grey background


def test_frames_subset_and_out_of_range(seqs):
    ds = SequenceDataset(seqs[0], frames=[3, 1])
    assert len(ds) == 2 and ds[0].index == 3 and ds[1].index == 1
    with pytest.raises(IndexError, match="4"):
        SequenceDataset(seqs[0], frames=[0, 4])


def test_ground_truth_modes(seqs):
    a, _ = seqs
    assert SequenceDataset(a).with_gt  # "auto" picks up gt/
    f = SequenceDataset(a, ground_truth=False)[0]  # tracker mode
    assert f.theta is None and f.keypoints_3d is None and f.keypoints_2d is None and f.model_ids is None
    assert f.depth.shape == (1, H, W)
    assert SequenceDataset(a, ground_truth=True)[0].theta is not None


def test_works_without_gt_folder(seq_copy):
    shutil.rmtree(seq_copy / "gt")
    ds = SequenceDataset(seq_copy)
    assert len(ds) == 4 and not ds.with_gt
    f = ds[2]
    assert f.theta is None and f.model_ids is None and f.depth.shape == (1, H, W)
    b = collate_frames([ds[0], ds[1]])
    assert b.theta is None and b.depth.shape == (2, 1, H, W)
    with pytest.raises(SequenceError, match="gt"):
        SequenceDataset(seq_copy, ground_truth=True)


def test_dataloader_with_workers_stacks(seqs):
    ds = SequenceDataset(seqs[0], rgb=True)
    loader = DataLoader(ds, batch_size=2, num_workers=2, collate_fn=collate_frames)
    batches = list(loader)
    assert len(batches) == 2
    b = batches[1]
    assert isinstance(b, Frame)
    assert b.depth.shape == (2, 1, H, W) and b.rgb.shape == (2, 1, H, W, 3)
    assert b.K.shape == (2, 1, 3, 3) and b.T_cw.shape == (2, 1, 4, 4)
    assert b.theta.shape == (2, 37) and b.keypoints_3d.shape == (2, 1, 21, 3)
    assert b.keypoints_2d.shape == (2, 1, 21, 2) and b.model_ids.shape == (2, H, W)
    assert torch.equal(b.index, torch.tensor([2, 3]))
    assert b.sequence == ["random_0", "random_0"]
    torch.testing.assert_close(b.depth[0], ds[2].depth)
    torch.testing.assert_close(b.theta[1], ds[3].theta)


def test_multi_sequence_mixed_scenes(seqs):
    a, b = seqs
    ds = MultiSequenceDataset([a, b])
    assert len(ds) == 6
    assert ds[4].sequence == "random_1" and ds[4].index == 0
    assert ds[4].theta.shape == (43,)  # hand_right (37) + ball (6)
    same = collate_frames([ds[0], ds[1]])
    assert isinstance(same.theta, torch.Tensor) and same.theta.shape == (2, 37)
    mixed = collate_frames([ds[3], ds[4]])
    assert isinstance(mixed.theta, list) and [t.shape for t in mixed.theta] == [(37,), (43,)]
    assert mixed.sequence == ["random_0", "random_1"]
    assert torch.equal(mixed.index, torch.tensor([3, 0]))
    # equal shapes are still stacked: the ball has no keypoints, images have one size
    assert mixed.depth.shape == (2, 1, H, W) and mixed.keypoints_3d.shape == (2, 1, 21, 3)
    assert set(mixed.model_ids[1].unique().tolist()) <= {-1, 0, 1}
    # the same through a DataLoader whose batch spans both sequences
    batch = next(iter(DataLoader(ds, batch_size=6, collate_fn=collate_frames)))
    assert isinstance(batch.theta, list) and len(batch.theta) == 6
    assert [t.shape[0] for t in batch.theta] == [37] * 4 + [43] * 2


def test_multi_sequence_needs_a_folder():
    with pytest.raises(ValueError):
        MultiSequenceDataset([])


def test_deleted_depth_frame_names_path(seq_copy):
    ds = SequenceDataset(seq_copy)
    missing = seq_copy / "depth" / frame_name(2)
    missing.unlink()
    ds[1]  # other frames still load
    with pytest.raises(SequenceError) as err:
        ds[2]
    assert str(missing) in str(err.value)


def test_deleted_rgb_frame_names_path(seq_copy):
    ds = SequenceDataset(seq_copy, rgb=True)
    missing = seq_copy / "rgb" / frame_name(0)
    missing.unlink()
    with pytest.raises(SequenceError) as err:
        ds[0]
    assert str(missing) in str(err.value)


def test_gt_frame_count_mismatch(seq_copy):
    theta = np.load(seq_copy / "gt" / "theta.npy")
    for n in ("theta", "keypoints_3d", "keypoints_2d"):
        np.save(seq_copy / "gt" / f"{n}.npy", np.load(seq_copy / "gt" / f"{n}.npy")[:3])
    assert len(theta) == 4
    ds = SequenceDataset(seq_copy)
    with pytest.raises(SequenceError, match="3 frames"):
        ds[0]


def test_missing_sequence_json(tmp_path):
    with pytest.raises(SequenceError, match="sequence.json"):
        SequenceDataset(tmp_path)
