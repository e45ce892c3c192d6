"""Layer 4: articulated models: kinematics (twists, FK), linear blend skinning, models and
scenes (assets as buffers, poses as inputs), MOTION rows <-> theta, URDF export, and the
fingertip vertex sets."""

from torchhand.model.articulated import ArticulatedModel, ModelOutput, load_model  # noqa: F401
from torchhand.model.scene import Scene, SceneOutput  # noqa: F401
