"""torchhand: capture the 3D motion of hands in action with batched, differentiable
articulated models in PyTorch (after Tzionas, PhD thesis 2016, and Ballan et al., ECCV 2012)."""

from .io.assets import FINGER_NAMES, HAND_KEYPOINT_NAMES, available_models  # noqa: F401
from .model import ArticulatedModel, ModelOutput, load_model  # noqa: F401
from .scene import Scene, SceneOutput  # noqa: F401

__version__ = "0.1.0"
