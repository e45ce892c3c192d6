"""Draw the standard 21 joints on the shipped hands (docs/joints21.png).

    PYTHONPATH=. python eval/draw_joints21.py --out docs/joints21.png

Each hand is posed palm towards the camera, fingers up, slightly spread, rendered with
flat shading, and its 21 joints (torchhand.model.joints21) are drawn with their numbers:
0 the wrist, then thumb, index, middle, ring, little from the base outwards.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import torch

from torchhand import load_model
from torchhand.geometry.camera import kinect_camera
from torchhand.geometry.render import render
from torchhand.model.joints21 import standard_joints
from torchhand.model.kinematics import so3_log

FINGER_BGR = [(60, 60, 230), (40, 170, 40), (220, 130, 30), (30, 180, 220), (200, 60, 200)]


def _facing_pose(model, distance: float = 380.0) -> torch.Tensor:
    """(1, D) the rest pose turned palm to the camera, fingers up (image -y), wrist low."""
    theta = model.zero_pose(1)
    out = model(theta)
    j = standard_joints(out, model)[0]
    up = torch.nn.functional.normalize(j[9] - j[0], dim=0)
    across = j[17] - j[5]  # index base -> little base
    palm = torch.nn.functional.normalize(torch.linalg.cross(up, across), dim=0)
    if model.side == "left":
        palm = -palm
    # camera frame: x right, y down, z forward. R up = -y (fingers up in the image) and
    # R palm = -z (the palm faces the camera): R's rows are up x palm, -up, -palm.
    R = torch.stack([torch.linalg.cross(up, palm), -up, -palm])
    theta[0, 3:6] = so3_log(R[None])[0]
    centre = out.vertices[0].mean(0)
    theta[0, :3] = torch.tensor([0.0, 0.0, distance], dtype=j.dtype) - R @ (centre - j[0]) - j[0]
    return theta


def draw_hand(name: str) -> np.ndarray:
    model = load_model(name, dtype=torch.float64)
    theta = _facing_pose(model)
    out = model(theta)
    cam = kinect_camera(dtype=torch.float64)
    res = render(out.vertices.float(), model.faces, cam.to(dtype=torch.float32))
    shade = (res.normals[0, ..., 2].abs() * 150 + 80).clamp(0, 255).numpy().astype(np.uint8)
    img = np.where(res.depth[0].numpy()[..., None] > 0, shade[..., None], 255).astype(np.uint8).repeat(3, -1)
    img = np.ascontiguousarray(img)
    px = cam.project(standard_joints(out, model))[0].numpy()
    for f in range(5):
        chain = [0] + list(range(1 + 4 * f, 5 + 4 * f))
        for a, b in zip(chain[:-1], chain[1:]):
            cv2.line(img, tuple(np.round(px[a]).astype(int)), tuple(np.round(px[b]).astype(int)), FINGER_BGR[f], 2,
                     cv2.LINE_AA)
    for k, p in enumerate(px):
        colour = (0, 0, 0) if k == 0 else FINGER_BGR[(k - 1) // 4]
        q = tuple(np.round(p).astype(int))
        cv2.circle(img, q, 4, colour, -1, cv2.LINE_AA)
        cv2.putText(img, str(k), (q[0] + 5, q[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"{name}, palm to the camera", (10, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1,
                cv2.LINE_AA)
    return img


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", default="docs/joints21.png", help="PNG to write")
    args = parser.parse_args(argv)
    panels = [draw_hand(n) for n in ("hand_right", "hand_left")]
    legend = np.full((60, panels[0].shape[1] * 2, 3), 255, np.uint8)
    text = ("0 wrist; thumb 1-4 (CMC, MCP, IP, tip); index 5-8, middle 9-12, ring 13-16, little 17-20 "
            "(MCP, PIP, DIP, tip)")
    cv2.putText(legend, text, (10, 35), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(args.out, np.vstack([np.hstack(panels), legend]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
