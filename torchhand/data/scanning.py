"""In-hand scanning sequences (thesis Ch. 5): a hand holds an object and turns it in
front of the camera; the object is unknown to the tracker and is what a scan recovers.

:func:`grasp` closes the shipped hand around a mesh: the object is placed in front of
the palm, then every finger (the thumb along the path that brings its tip to the
object) flexes until it touches the surface or its joints reach their limits; the
fingers that stopped on the surface are the grasp's contacts. :func:`scan_motion` turns
the hand and object as one rigid unit about the object's centre: two full turns about
the camera's vertical axis while the object tilts by up to ``tilt`` degrees towards and
away from the camera, so that its top and bottom come into view as well (a turntable's
views, held by a hand; a wrist cannot turn 720 degrees, a person regrasps, which the
synthetic sequence leaves out). A spin about the palm's normal, which keeps the object
in front of the hand, was tried: the hand seen palm-on with curled fingers was lost by
the tracker after 80 frames (docs/scanning.md). :func:`write_scan_sequence` renders it with
the sensor noise into the sequence layout: ``sequence.json`` lists the hand only
(the object is what the scan must find), ``gt/`` holds the hand's poses as usual plus
``gt/object_pose.npy`` (N, 4, 4), the transform from the mesh's own coordinates to
camera coordinates per frame, and ``gt/object.ply``, the mesh itself.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional

import numpy as np
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.io.assets import rigid_assets
from torchhand.io.mesh_files import ObjectMesh, read_object_mesh, write_mesh
from torchhand.model.articulated import ArticulatedModel, load_model
from torchhand.model.kinematics import so3_log
from torchhand.model.scene import Scene
from torchhand.model.shape import finger_bones
from torchhand.data.layout import SequenceLayout
from torchhand.data.synth import SyntheticFrames, quat_to_matrix, write_synthetic_sequence

__all__ = ["Grasp", "grasp", "scan_motion", "write_scan_sequence", "scan_frames", "OBJECT_NAME"]

#: the scene name of the scanned object in synthesis (not listed in sequence.json)
OBJECT_NAME = "object"
#: degrees the grasp turns per frame by default (two turns in 180 frames)
DEGREES_PER_FRAME = 4.0
# flexion profile along a finger (proximal, middle, distal bone) of the closing motion
_PROFILE = (0.75, 1.0, 0.8)


class Grasp(NamedTuple):
    """theta: (D,) the hand's pose with its root at the identity; object_to_hand: (4, 4)
    the transform from the mesh's coordinates to the hand's (root) frame; contacts: the
    fingers resting on the surface; gap: mm between the palm and the object; normal,
    length: (3,) the palm's normal (towards the object) and the wrist-to-fingers axis,
    in the hand's frame."""

    theta: np.ndarray
    object_to_hand: np.ndarray
    contacts: List[str]
    gap: float
    normal: np.ndarray
    length: np.ndarray


def _occupancy(mesh: ObjectMesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))

    def inside(points: np.ndarray) -> np.ndarray:
        return scene.compute_occupancy(o3d.core.Tensor(points.astype(np.float32))).numpy() > 0.5

    return inside


def grasp(hand: ArticulatedModel, mesh: ObjectMesh, gap: Optional[float] = None, seed: int = 0,
          steps: int = 12) -> Grasp:
    """Close ``hand`` (a shipped hand model) around ``mesh``.

    ``gap`` None: the largest of 20, 12 and 5 mm at which the thumb and at least one
    finger touch the object (a grasp held by the finger tips leaves more of the object in
    view than one that wraps it); the 5 mm grasp when none does.

    The object, turned by a random rotation drawn from ``seed``, is placed in front of
    the palm at ``gap`` mm from it, its centre over the bases of the middle fingers;
    each finger's joints close in turn from the knuckle out, each bisected (``steps``
    halvings) for the largest flexion at which none of the links it moves is inside the
    object (the closing rule of grasp planners); the thumb moves along the straight
    path in its joint space towards the posture that brings its tip nearest to the
    object's centre, until it touches.
    """
    if gap is None:
        for g in (20.0, 12.0, 5.0):
            best = grasp(hand, mesh, g, seed, steps)
            if "thumb" in best.contacts and len(best.contacts) >= 2:
                break
        return best
    inside = _occupancy(mesh)
    theta = hand.zero_pose(1)[0].clone()
    fingers = {f: [int(b) for b in bones] for f, bones in finger_bones(hand).items()}
    names = list(hand.keypoint_names)
    kp = hand(theta[None]).keypoints[0].double().numpy()
    at = {n: kp[names.index(n)] for n in names}
    # palm frame: length axis wrist -> middle MCP, palmar normal = where the fingers curl
    length = at["middle_mcp"] - at["wrist"]
    length /= np.linalg.norm(length)
    curled = _flexed(hand, theta, fingers["middle"], 1.0)
    tip_moves = hand(curled[None]).keypoints[0].double().numpy()[names.index("middle_tip")] - at["middle_tip"]
    normal = tip_moves - length * (tip_moves @ length)
    normal /= np.linalg.norm(normal)
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    R = quat_to_matrix(torch.as_tensor(q / np.linalg.norm(q))).numpy()
    centred = mesh.vertices - mesh.vertices.mean(0)
    turned = centred @ R.T
    base = (at["index_mcp"] + at["middle_mcp"] + at["ring_mcp"] + at["little_mcp"]) / 4
    palm_vertices = hand(theta[None]).vertices[0].double().numpy()
    # the palm's surface along the normal, under the object's footprint
    palm_top = (palm_vertices[np.linalg.norm(np.cross(palm_vertices - base, normal), axis=1) < 25.0] - base) @ normal
    height = (palm_top.max() if len(palm_top) else 0.0) + gap - (turned @ normal).min()
    centre = base + normal * height - length * 10.0
    to_hand = np.eye(4)
    to_hand[:3, :3] = R
    to_hand[:3, 3] = centre - R @ mesh.vertices.mean(0)
    local = _ObjectInHand(inside, to_hand)
    contacts = []
    for f in ("index", "middle", "ring", "little"):
        touched = False
        for k, j in enumerate(fingers[f]):  # proximal, middle, distal: each joint closes until its links touch
            d = hand.dof_index(f"{hand.bone_names[j]}:y")
            lo = float(hand.lower[d])

            def bent(t, s, d=d, lo=lo):
                out = t.clone()
                out[d] = s * lo
                return out

            s = _close(hand, theta, bent, fingers[f][k:], local, steps)
            theta = bent(theta, s)
            touched |= s < 1.0
        if touched:
            contacts.append(f)
    thumb_path = _thumb_path(hand, theta, fingers["thumb"], centre)
    s = _close(hand, theta, lambda t, s: t + s * (thumb_path - t), fingers["thumb"], local, steps)
    theta = theta + s * (thumb_path - theta)
    if s < 1.0:
        contacts.append("thumb")
    return Grasp(theta.double().numpy(), to_hand, contacts, float(gap), normal, length)


class _ObjectInHand:
    def __init__(self, inside, to_hand):
        self.inside, self.inv = inside, np.linalg.inv(to_hand)

    def __call__(self, points_hand: np.ndarray) -> bool:
        return bool(self.inside(points_hand @ self.inv[:3, :3].T + self.inv[:3, 3]).any())


def _finger_vertices(hand: ArticulatedModel, bones: List[int]) -> torch.Tensor:
    return torch.nonzero(torch.isin(hand.vertex_bone, torch.as_tensor(bones)))[:, 0]


def _flexed(hand: ArticulatedModel, theta: torch.Tensor, bones: List[int], s: float) -> torch.Tensor:
    """theta with the flexion (y) slots of a finger's last three bones at ``s`` times
    their flexion limit (the profile of _PROFILE along the finger)."""
    out = theta.clone()
    chain = bones[-3:]
    for k, j in enumerate(chain):
        name = f"{hand.bone_names[j]}:y"
        if name in hand.dof_names:
            d = hand.dof_index(name)
            lo = float(hand.lower[d])
            out[d] = s * _PROFILE[k] * lo
    return out


def _close(hand, theta, pose_at, bones, local, steps) -> float:
    """The largest s in [0, 1] at which the finger (its bones' vertices) is outside the object."""
    ids = _finger_vertices(hand, bones)

    def free(s: float) -> bool:
        v = hand(pose_at(theta, s)[None]).vertices[0, ids].double().numpy()
        return not local(v)

    if free(1.0):
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(steps):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if free(mid) else (lo, mid)
    return lo


def _thumb_path(hand: ArticulatedModel, theta: torch.Tensor, bones: List[int], target: np.ndarray) -> torch.Tensor:
    """The thumb posture (within its limits) whose tip comes nearest to ``target``: a
    grid over the thumb's DoF, then the best cell refined by a finer grid."""
    dofs = [d for d, n in enumerate(hand.dof_names) if n.split(":")[0] in {hand.bone_names[j] for j in bones}]
    lo, hi = hand.lower[dofs].double(), hand.upper[dofs].double()
    tip = hand.keypoint_names.index("thumb_tip")
    best = theta.clone()
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    for _ in range(3):
        grid = torch.stack(torch.meshgrid(*[torch.linspace(-1, 1, 4, dtype=torch.float64)] * len(dofs),
                                          indexing="ij"), -1).reshape(-1, len(dofs))
        cand = (centre + grid * half).clamp(lo, hi)
        th = best[None].repeat(len(cand), 1)
        th[:, dofs] = cand.to(th.dtype)
        fk = hand.kinematics(th)
        tips = hand.keypoints_from(fk.G)[:, tip].double().numpy()
        k = int(np.argmin(np.linalg.norm(tips - target, axis=1)))
        best = th[k]
        centre, half = cand[k], half / 3
    return best


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    R = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def scan_frames(turns: float = 2.0, degrees_per_frame: float = DEGREES_PER_FRAME) -> int:
    """The default length of a scan: ``turns`` full turns at ``degrees_per_frame``."""
    return int(round(360.0 * turns / degrees_per_frame))


def scan_motion(mesh: ObjectMesh, hand_name: str = "hand_right", frames: Optional[int] = None, seed: int = 0,
                distance: Optional[float] = None, tilt: float = 40.0, turns: float = 2.0,
                dtype=torch.float64) -> SyntheticFrames:
    """The grasp of :func:`grasp` turned in front of the thesis camera.

    The object's centre stays ``distance`` mm in front of the camera (None: 550 mm, or
    450 mm plus the object's largest distance from its centre, so that no part of it
    comes nearer than the Kinect's 400 mm minimum range as it turns); at frame k the
    unit has turned by ``turns * 360 * k / frames`` degrees about the camera's vertical
    axis and is tilted by ``tilt * sin(3 pi k / frames)`` degrees about its horizontal
    axis. Returns frames of the scene ``[hand_name, "object"]`` with the object hidden
    from the sequence's declared models; ``source["object_pose"]`` holds the (N, 4, 4)
    mesh-to-camera transforms and ``source["grasp"]`` the contacts.
    """
    if frames is None:
        frames = scan_frames(turns)
    if frames < 2:
        raise ValueError(f"a scan needs at least 2 frames, got {frames}")
    hand = load_model(hand_name, dtype=dtype)
    if hand.kind != "hand":
        raise ValueError(f"--hand {hand_name!r} is not a hand model")
    g = grasp(hand, mesh, seed=seed)
    if distance is None:
        reach = float(np.linalg.norm(mesh.vertices - mesh.vertices.mean(0), axis=1).max())  # about its centre
        distance = max(550.0, 450.0 + reach)
    obj = ArticulatedModel(rigid_assets(OBJECT_NAME, mesh.vertices, mesh.faces, source=str(mesh.path or "")),
                           dtype=dtype)
    scene = Scene([hand, obj], [hand_name, OBJECT_NAME])
    centre_mesh = mesh.vertices.mean(0)
    centre_hand = g.object_to_hand[:3, :3] @ centre_mesh + g.object_to_hand[:3, 3]
    # start: palm towards the camera's right, the object in front of the hand; then two
    # turns about the camera's vertical axis while tilting about its horizontal axis
    R0 = _rot(1, -math.pi / 2)
    root = hand.rest_transforms[0, :3, 3].double().numpy()
    theta = np.zeros((frames, scene.num_dofs))
    poses = np.zeros((frames, 4, 4))
    for k in range(frames):
        R = (_rot(1, 2 * math.pi * turns * k / frames) @ _rot(0, math.radians(tilt) * math.sin(3 * math.pi * k / frames))
             @ R0)
        # hand frame -> camera: x -> R (x - centre_hand) + P
        A_R, A_t = R, np.array([0.0, 0.0, distance]) - R @ centre_hand
        th_hand = g.theta.copy()
        th_hand[3:6] = so3_log(torch.as_tensor(A_R)[None])[0].numpy()
        th_hand[0:3] = A_t + A_R @ root - root
        T_obj = np.eye(4)
        T_obj[:3, :3] = A_R @ g.object_to_hand[:3, :3]
        T_obj[:3, 3] = A_R @ g.object_to_hand[:3, 3] + A_t
        poses[k] = T_obj
        th_obj = np.concatenate([T_obj[:3, 3], so3_log(torch.as_tensor(T_obj[:3, :3])[None])[0].numpy()])
        theta[k] = np.concatenate([th_hand, th_obj])
    source = {"format": "in-hand scan", "mesh": str(mesh.path or ""), "seed": seed, "turns": turns,
              "tilt_degrees": tilt, "grasp": {"contacts": g.contacts, "gap_mm": g.gap}}
    sf = SyntheticFrames(scene, torch.as_tensor(theta, dtype=dtype), [kinect_camera(dtype=dtype)],
                         f"scan_{Path(mesh.path).stem if mesh.path else 'object'}", source, hidden=(OBJECT_NAME,))
    sf.source["object_pose"] = poses
    return sf


def write_scan_sequence(mesh_path, out, hand: str = "hand_right", frames: Optional[int] = None,
                        noise: str = "kinect", seed: int = 0, force: bool = False, progress: bool = True,
                        backend: Optional[str] = None, turns: float = 2.0) -> Path:
    """``torchhand synth --scan-object``: render an in-hand scan of the mesh at
    ``mesh_path`` (see the module docstring) into the new sequence folder ``out``;
    ``turns``: full turns over the ``frames`` (default: two turns at 4 degrees a frame)."""
    mesh = read_object_mesh(mesh_path)
    sf = scan_motion(mesh, hand, frames=frames, seed=seed, turns=turns)
    poses = sf.source.pop("object_pose")
    out = write_synthetic_sequence(sf, out, noise=noise, seed=seed, force=force, progress=progress, backend=backend)
    gt = SequenceLayout(out).gt
    np.save(gt.object_pose, poses)
    write_mesh(gt.object_mesh, mesh.vertices, mesh.faces)
    meta: Dict = {"mesh": str(mesh.path), "object_pose": "object_pose.npy: (N, 4, 4) mesh -> camera, mm",
                  "contacts": sf.source["grasp"]["contacts"]}
    gt.object_meta.write_text(json.dumps(meta, indent=1))
    return out
