"""Weight files of the project's networks: ``{"format", "config", "state_dict"}`` written
with :func:`torch.save` and read back with ``weights_only=True``, every error naming the
file and what is wrong. :class:`~torchhand.salient.detector.SalientNet` and
:class:`~torchhand.salient.localiser_net.LocaliserNet` save and load through it."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from torch import nn

__all__ = ["save_weights", "load_weights"]


def save_weights(net: nn.Module, path, fmt: str) -> Path:
    """Write ``net``'s config (a dataclass at ``net.config``) and weights, tagged ``fmt``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    torch.save({"format": fmt, "config": asdict(net.config), "state_dict": state}, path)
    return path


def load_weights(cls, config_cls, path, fmt: str, what: str, map_location="cpu") -> nn.Module:
    """The network ``cls(config_cls(**config))`` of a file written by :func:`save_weights`
    with the tag ``fmt``; ``what`` names the kind of network in errors."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} weights not found")
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # pickle, zip and torch errors all mean the same here
        raise ValueError(f"{path}: not a readable torch weights file ({type(e).__name__}: {e})") from None
    if not isinstance(blob, dict) or blob.get("format") != fmt:
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise ValueError(f"{path}: not {what} weights (format {found!r}, expected {fmt!r})")
    try:
        config = config_cls(**blob["config"])
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"{path}: invalid network config: {e}") from None
    net = cls(config)
    try:
        net.load_state_dict(blob["state_dict"])
    except (RuntimeError, KeyError) as e:
        raise ValueError(f"{path}: weights do not fit the network of its config {config}: {e}") from None
    return net.to(map_location).eval()
