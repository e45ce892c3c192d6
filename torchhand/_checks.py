"""Input validation at the public boundary (shapes, dtypes, devices, finiteness)."""

from __future__ import annotations

from typing import Sequence

import torch


def check_tensor(
    x,
    name: str,
    shape: Sequence[int | str | None],
    dtype: torch.dtype | None = None,
    device: torch.device | None = None,
    finite: bool = True,
) -> torch.Tensor:
    """Raise a clear error unless ``x`` is a tensor of the given shape.

    ``shape`` entries: an int must match exactly, a str/None matches any size
    (the str names the dimension in the message, e.g. ``("B", 37)``).
    """
    want = "(" + ", ".join(str(s) if s is not None else "*" for s in shape) + ")"
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {want}, got {type(x).__name__}")
    if x.dim() != len(shape) or any(isinstance(s, int) and s != n for s, n in zip(shape, x.shape)):
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"{name} must have dtype {dtype}, got {x.dtype}")
    if device is not None and x.device != torch.device(device) and not _same_device(x.device, device):
        raise ValueError(f"{name} is on {x.device} but the model is on {device}; move one with .to()")
    if finite and x.is_floating_point() and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return x


def _same_device(a: torch.device, b) -> bool:
    b = torch.device(b)
    return a.type == b.type and (a.index is None or b.index is None or a.index == b.index)
