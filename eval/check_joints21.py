"""Where the standard 21 joints put the fingertips on the shipped hands (docs/model.md):
how far beyond the end of the distal bone (the model's own tip keypoint), and how far off
the bone's axis, at the zero pose.

    python eval/check_joints21.py
"""

import torch
from torchhand import load_model
from torchhand.model.joints21 import standard_joints
for name in ("hand_right", "hand_left"):
    m = load_model(name, dtype=torch.float64)
    out = m(m.zero_pose(1))
    j = standard_joints(out, m)[0]
    tips, dip, end = j[[4, 8, 12, 16, 20]], j[[3, 7, 11, 15, 19]], out.keypoints[0, [4, 8, 12, 16, 20]]
    axis = (end - dip) / (end - dip).norm(dim=-1, keepdim=True)
    beyond = ((tips - end) * axis).sum(-1)
    off = (tips - end - beyond[:, None] * axis).norm(dim=-1)
    print(name, "beyond mm", [round(float(x), 2) for x in beyond], "off-axis mm", [round(float(x), 2) for x in off])
