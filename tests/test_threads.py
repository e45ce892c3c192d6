"""Intra-op thread counts of the tracker's frame loop (torchhand.core.threads)."""

from __future__ import annotations

import pytest
import torch

from torchhand.core.threads import intra_op_threads
from torchhand.tracking.tracker import TrackerConfig


def test_intra_op_threads_caps_the_block_and_restores_the_count():
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with intra_op_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with intra_op_threads(None), intra_op_threads(4):  # None: as it is; never more than set
            assert torch.get_num_threads() == 2
        with pytest.raises(KeyError):
            with intra_op_threads(1):
                raise KeyError("x")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(old)


def test_tracker_threads_default_to_one_and_are_checked():
    assert TrackerConfig().threads == 1 and TrackerConfig(threads=None).threads is None
    with pytest.raises(ValueError, match="threads"):
        TrackerConfig(threads=0)
    with pytest.raises(ValueError, match="fused"):
        TrackerConfig(fused=1)
