"""File formats: the thesis' model and motion files, and torchhand's model assets."""

from torchhand.io.assets import (  # noqa: F401
    FINGER_NAMES,
    HAND_KEYPOINT_NAMES,
    THESIS_MODEL_NAMES,
    ModelAssets,
    assets_from_thesis,
    available_models,
    find_model,
    load_assets,
    save_assets,
)
from torchhand.io.thesis import *  # noqa: F401,F403
