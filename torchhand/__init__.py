"""torchhand: capture the 3D motion of hands in action with batched, differentiable
articulated models in PyTorch (after Tzionas, PhD thesis 2016, and Ballan et al., ECCV 2012).

The entry points below are loaded on first use, so that importing one layer
(``import torchhand.geometry.camera``) does not import the layers above it.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: name -> module that defines it
_EXPORTS = {
    "ArticulatedModel": "torchhand.model.articulated",
    "ModelOutput": "torchhand.model.articulated",
    "load_model": "torchhand.model.articulated",
    "Scene": "torchhand.model.scene",
    "SceneOutput": "torchhand.model.scene",
    "FINGER_NAMES": "torchhand.io.assets",
    "HAND_KEYPOINT_NAMES": "torchhand.io.assets",
    "available_models": "torchhand.io.assets",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchhand' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
