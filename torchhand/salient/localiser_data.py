"""Training and test frames for the hand localiser: rendered hands in a real context.

A real depth frame holds much more than floating hands: the forearm and upper arm, the
shoulder, torso and head of the person, a table, held objects, a second person's arm,
clutter at any range. The localiser (:mod:`torchhand.salient.localiser`) learns to
tell the hands apart from all of that on renders alone, so every frame is built here
from the shipped hands and simple procedural shapes (capsules, boxes, spheres,
cylinders) and rendered by the project's renderer in one pass:

- **hands**: the shipped left and right models, one or both, resized per frame (global
  scale and per-finger length factors, the range ``torchhand calibrate`` fits), posed
  by the thesis motions' finger articulations, by poses uniform within the joint limits,
  or by per-finger curls (open, half-closed, fists, pinches: each finger's flexion
  joints at one random share of their limit);
- **the person**: each hand ends in a forearm and an upper arm placed by two-link
  inverse kinematics from a shoulder of a torso box with a head; third-person views
  (the person faces the camera; the arm reaches toward the camera as often as
  sideways) and egocentric ones (the camera at the head, the arms entering from below);
- **the scene**: a table top under the hands, an object held in the palm, a second
  person's arm, clutter boxes, spheres and cylinders at 0.3-3 m, a tilted wall/floor
  plane and boxes behind everything (:func:`~torchhand.salient.training_data.random_background`);
- **the camera**: 640x480 with a focal length drawn per batch (380-620 px: RealSense
  and Kinect-type sensors at VGA), tilted per frame;
- **the sensor**: the Kinect model (:mod:`torchhand.data.noise`, training) or the
  independent active-stereo model (:mod:`torchhand.data.stereo_noise`, the test set).

Per frame: depth (uint16 mm, 0 = invalid), a label per pixel (:data:`CLASSES`; 255
where the sensor gave no depth), and the standard 21 joints of each hand
(:mod:`torchhand.model.joints21`) as image position and depth, NaN for an absent hand.
Hand 0 is the left hand, hand 1 the right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import List, NamedTuple, Optional, Sequence

import numpy as np
import torch
import trimesh
from tqdm import tqdm

from torchhand.data.noise import apply_kinect_noise
from torchhand.data.noise_params import noise_model
from torchhand.data.stereo_noise import StereoNoise, apply_stereo_noise
from torchhand.geometry.camera import Camera
from torchhand.geometry.render import Renderer
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.joints21 import joint_sources
from torchhand.model.kinematics import so3_exp
from torchhand.model.shape import FINGERS, bone_scales, pose_resized
from torchhand.salient.training_data import random_background

__all__ = ["CLASSES", "HANDS", "IGNORE", "ContextConfig", "LocaliserFrames", "render_context_frames",
           "hand_articulations", "concat_localiser_frames", "save_localiser_frames", "load_localiser_frames"]

#: Pixel classes of the label map.
CLASSES = ("background", "left_hand", "right_hand", "body")
#: The hand models, in the order of the joints arrays (hand 0 left, hand 1 right).
HANDS = ("hand_left", "hand_right")
#: Label of pixels without a sensor measurement (no loss).
IGNORE = 255

# the primitive slots rendered with the hands: (name, template, class)
_SLOTS = (("forearm_l", "capsule", 3), ("upper_l", "capsule", 3), ("forearm_r", "capsule", 3),
          ("upper_r", "capsule", 3), ("torso", "box", 3), ("head", "sphere", 3), ("other_arm", "capsule", 3),
          ("table", "box", 0), ("held_sphere", "sphere", 0), ("held_box", "box", 0), ("held_cyl", "cylinder", 0),
          ("clutter_box1", "box", 0), ("clutter_box2", "box", 0), ("clutter_sphere", "sphere", 0),
          ("clutter_cyl", "cylinder", 0))


@dataclass(frozen=True)
class ContextConfig:
    """Draw probabilities and ranges of :func:`render_context_frames` (module doc)."""

    distance_mm: tuple = (300.0, 1500.0)
    p_two_hands: float = 0.3
    p_egocentric: float = 0.35
    p_toward_camera: float = 0.5
    p_table: float = 0.4
    p_held: float = 0.35
    p_other_arm: float = 0.25
    p_clutter: float = 0.6
    focal_px: tuple = (380.0, 620.0)
    scale: tuple = (0.85, 1.15)
    finger_factor: tuple = (0.92, 1.08)
    noise: str = "kinect"  # "kinect" (training) or "stereo" (test), or "none"
    width: int = 640
    height: int = 480


class LocaliserFrames(NamedTuple):
    """depth (N, H, W) uint16 mm; labels (N, H, W) uint8 (:data:`CLASSES`, :data:`IGNORE`);
    joints_uv (N, 2, 21, 2) float32 px; joints_z (N, 2, 21) float32 mm (NaN: hand absent);
    K (N, 3, 3) float32 intrinsics; name (N,) provenance."""

    depth: np.ndarray
    labels: np.ndarray
    joints_uv: np.ndarray
    joints_z: np.ndarray
    K: np.ndarray
    name: np.ndarray


def _template(kind: str) -> tuple:
    """Unit primitive (vertices, faces) of a slot: capsule/cylinder along +z from 0 to 1
    with radius 1, box and sphere centred with half-size/radius 1."""
    if kind == "capsule":
        m = trimesh.creation.capsule(height=1.0, radius=0.5, count=[10, 10])
        v = np.asarray(m.vertices) * np.array([2.0, 2.0, 0.5]) + np.array([0, 0, 0.5])  # caps squashed to [0, 1]
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=16)
        v = np.asarray(m.vertices) + np.array([0, 0, 0.5])
    elif kind == "box":
        m = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
        m = m.subdivide().subdivide()  # small triangles rasterise without long slivers
        v = np.asarray(m.vertices)
    else:
        m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        v = np.asarray(m.vertices)
    return v.astype(np.float32), np.asarray(m.faces, np.int64)


class _Meshes:
    """The hands and the primitive slots as one renderer (the face class of each face)."""

    def __init__(self, models: Sequence[ArticulatedModel]):
        faces, cls, parts = [], [], []
        offset = 0
        for k, m in enumerate(models):
            faces.append(m.faces.long() + offset)
            cls.append(torch.full((len(m.faces),), 1 + k, dtype=torch.uint8))
            parts.append(("hand", m.num_vertices))
            offset += m.num_vertices
        self.templates = {}
        for name, kind, c in _SLOTS:
            if kind not in self.templates:
                self.templates[kind] = _template(kind)
            v, f = self.templates[kind]
            faces.append(torch.from_numpy(f) + offset)
            cls.append(torch.full((len(f),), c, dtype=torch.uint8))
            parts.append((name, len(v)))
            offset += len(v)
        self.faces = torch.cat(faces).int()
        self.face_class = torch.cat(cls)
        self.parts = parts
        self.renderer = Renderer(self.faces)


def hand_articulations(model: ArticulatedModel, n: int, g: torch.Generator,
                       motion: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(n, D - 6) finger articulations of ``model``: a third from ``motion`` rows (the
    thesis motions; uniform draws when None), a third uniform within the joint limits,
    a third per-finger curls (each finger's flexion joints at one share of their limit,
    the other joints at up to half of theirs: open hands, half-closed, fists, pinches)."""
    lo, hi = model.lower[6:].float(), model.upper[6:].float()
    u = torch.rand(n, len(lo), generator=g)
    uniform = lo + u * (hi - lo)
    flex = lo < -0.6
    digit = torch.tensor([int(name.split("Fing.")[1][0]) if "Fing." in name else 0 for name in model.dof_names[6:]])
    curl = torch.rand(n, 5, generator=g) ** 0.7
    curl = torch.where(torch.rand(n, 5, generator=g) < 0.15, torch.zeros_like(curl), curl)
    fist = torch.rand(n, 1, generator=g) < 0.25
    curl = torch.where(fist, 0.8 + 0.2 * torch.rand(n, 5, generator=g), curl)
    jitter = 0.85 + 0.15 * torch.rand(n, len(lo), generator=g)
    side = lo + (0.25 + 0.5 * torch.rand(n, len(lo), generator=g)) * (hi - lo)
    curled = torch.where(flex, curl[:, digit] * lo * jitter, side)
    kind = torch.randint(0, 3, (n,), generator=g)
    out = torch.where((kind == 1)[:, None], uniform, curled)
    if motion is not None and len(motion):
        rows = motion[torch.randint(0, len(motion), (n,), generator=g)].float()
        out = torch.where((kind == 0)[:, None], rows, out)
    return torch.maximum(torch.minimum(out, hi), lo)


def _rand(g, lo, hi, *shape) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def _perpendicular(a: torch.Tensor, g) -> torch.Tensor:
    r = _unit(torch.randn(a.shape, generator=g, dtype=a.dtype))
    return _unit(r - (r * a).sum(-1, keepdim=True) * a)


def _rotation(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    return so3_exp(_unit(axis) * angle[..., None])


def _limb(a: torch.Tensor, b: torch.Tensor, r1: float, r2: float) -> torch.Tensor:
    """4x4 placing the unit capsule from ``a`` to ``b`` with radii (r1, r2)."""
    z = b - a
    L = z.norm()
    z = z / L.clamp_min(1e-6)
    x = _unit(torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=z.dtype) + 0.3 * torch.tensor([1.0, 0, 0], dtype=z.dtype)))
    y = torch.linalg.cross(z, x)
    T = torch.eye(4, dtype=z.dtype)
    T[:3, :3] = torch.stack([x * r1, y * r2, z * L], 1)
    T[:3, 3] = a
    return T


def _placed(R: torch.Tensor, half: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    T = torch.eye(4, dtype=R.dtype)
    T[:3, :3] = R * half[None, :]
    T[:3, 3] = centre
    return T


def _two_link(shoulder, wrist, l1, l2, down, g) -> tuple:
    """(shoulder, elbow): the elbow of an arm of segments l1, l2, preferring below; the
    shoulder is moved along the line when the wrist is out of reach."""
    d = wrist - shoulder
    dist = d.norm()
    lo, hi = abs(l1 - l2) + 40.0, l1 + l2 - 15.0
    if dist > hi or dist < lo:
        dist = min(max(float(dist), lo), hi)
        shoulder = wrist - _unit(d) * dist
        d = wrist - shoulder
    dist = float(d.norm())
    a = (l1 ** 2 - l2 ** 2 + dist ** 2) / (2 * dist)
    h = math.sqrt(max(l1 ** 2 - a ** 2, 0.0))
    u = _unit(d)
    side = down + 0.6 * torch.randn(3, generator=g, dtype=d.dtype)
    side = _unit(side - (side @ u) * u)
    return shoulder, shoulder + u * a + side * h


class _Frame:
    """The random draws of one frame (see :func:`render_context_frames`)."""

    def __init__(self, cfg: ContextConfig, g: torch.Generator, K: torch.Tensor, hands: Sequence[tuple]):
        self.cfg, self.g, self.K = cfg, g, K
        self.T = {}
        self.hand_pose = [None, None]  # per hand: (R, wrist position)
        two = float(torch.rand(1, generator=g)) < cfg.p_two_hands
        present = [True, True] if two else ([True, False] if float(torch.rand(1, generator=g)) < 0.5 else [False, True])
        self.present = present
        ego = float(torch.rand(1, generator=g)) < cfg.p_egocentric
        pitch = _rand(g, 0.3, 1.0, 1) if ego else _rand(g, -0.35, 0.35, 1)
        self.down = torch.tensor([0.0, math.cos(pitch), math.sin(pitch)], dtype=torch.float64)  # world down
        if ego:
            self._egocentric(hands)
        else:
            self._third_person(hands)
        self._scene()

    def _in_view(self, p: torch.Tensor, margin: float = 0.1) -> bool:
        if p[2] < 200:
            return False
        u = self.K[0, 0] * p[0] / p[2] + self.K[0, 2]
        v = self.K[1, 1] * p[1] / p[2] + self.K[1, 2]
        W, H = self.cfg.width, self.cfg.height
        return bool(margin * W < u < (1 - margin) * W and margin * H < v < (1 - margin) * H)

    def _view_point(self, z: float) -> torch.Tensor:
        W, H = self.cfg.width, self.cfg.height
        u, v = _rand(self.g, 0.15 * W, 0.85 * W, 1), _rand(self.g, 0.15 * H, 0.85 * H, 1)
        return torch.cat([(u - self.K[0, 2]) * z / self.K[0, 0], (v - self.K[1, 2]) * z / self.K[1, 1],
                          torch.tensor([z], dtype=torch.float64)])

    def _third_person(self, hands) -> None:
        g = self.g
        facing = _unit(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64) + 0.5 * torch.randn(3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.2, 0.0]))
        right = _unit(torch.linalg.cross(self.down, facing))  # the person's right
        z = float(_rand(g, *self.cfg.distance_mm, 1))
        target = self._view_point(z)
        first = 1 if self.present[1] else 0  # the hand placed at the target
        reach = _rand(g, 280.0, 540.0, 1)
        toward = float(torch.rand(1, generator=g)) < self.cfg.p_toward_camera
        if toward:
            direction = _unit(facing + 0.35 * torch.randn(3, generator=g, dtype=torch.float64))
        else:
            sign = 1.0 if first == 1 else -1.0
            direction = _unit(0.6 * facing + sign * right * _rand(g, 0.3, 1.0, 1) + self.down * _rand(g, -0.6, 0.8, 1))
        shoulder_first = target - direction * reach
        centre = shoulder_first - (right if first == 1 else -right) * 180.0
        self.body = (centre, facing, right)
        for k in (0, 1):
            if not self.present[k]:
                continue
            shoulder = centre + (right if k == 1 else -right) * 180.0
            wrist = target if k == first else target + _unit(torch.randn(3, generator=g, dtype=torch.float64)) * _rand(g, 90.0, 320.0, 1)
            self._arm(k, shoulder, wrist, hands[k])
        self.T["torso"] = _placed(torch.stack([right, self.down, -facing], 1), torch.tensor([190.0, 260.0, 110.0], dtype=torch.float64),
                                  centre + self.down * 250.0 - facing * 20.0)
        self.T["head"] = _placed(torch.eye(3, dtype=torch.float64), torch.tensor([80.0, 105.0, 95.0], dtype=torch.float64),
                                 centre - self.down * 230.0)

    def _egocentric(self, hands) -> None:
        g = self.g
        facing = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        right = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        centre = self.down * _rand(g, 180.0, 260.0, 1) - facing * _rand(g, 40.0, 120.0, 1)
        self.body = (centre, facing, right)
        for k in (0, 1):
            if not self.present[k]:
                continue
            shoulder = centre + (right if k == 1 else -right) * _rand(g, 150.0, 200.0, 1)
            for _ in range(20):
                wrist = shoulder + _unit(facing + 0.6 * torch.randn(3, generator=g, dtype=torch.float64)) * _rand(g, 300.0, 560.0, 1)
                if self._in_view(wrist, 0.12):
                    break
            else:
                wrist = self._view_point(float(_rand(g, 300.0, 550.0, 1)))
            self._arm(k, shoulder, wrist, hands[k])
        self.T["torso"] = _placed(torch.stack([right, self.down, facing], 1), torch.tensor([190.0, 260.0, 110.0], dtype=torch.float64),
                                  centre + self.down * 250.0)

    def _arm(self, k: int, shoulder, wrist, hand) -> None:
        g, scale = self.g, hand[0]
        shoulder, elbow = _two_link(shoulder, wrist, 300.0 * scale, 265.0 * scale, self.down, g)
        axis = _unit(wrist - elbow)
        # wrist flexion / deviation: the hand leaves the forearm's line by up to ~45 degrees
        bend = _rotation(_perpendicular(axis, g), _rand(g, -0.8, 0.8, 1))
        hand_axis = bend[0] @ axis
        normal = _perpendicular(hand_axis, g)
        self.hand_pose[k] = (torch.stack([hand_axis, normal, torch.linalg.cross(hand_axis, normal)], 1), wrist)
        r = 27.0 * scale
        self.T[f"forearm_{'lr'[k]}"] = _limb(wrist - axis * 28.0 * scale, elbow, r, 0.8 * r)
        self.T[f"upper_{'lr'[k]}"] = _limb(elbow, shoulder, 1.25 * r, 1.5 * r)

    def _scene(self) -> None:
        g, cfg = self.g, self.cfg
        wrists = [p[1] for p in self.hand_pose if p is not None]
        w = wrists[0]
        R_world = torch.stack([_perpendicular(self.down, g), self.down, torch.zeros(3, dtype=torch.float64)], 1)
        R_world[:, 2] = torch.linalg.cross(R_world[:, 0], R_world[:, 1])
        if float(torch.rand(1, generator=g)) < cfg.p_table:
            top = max(float((p @ self.down)) for p in wrists) + float(_rand(g, 30.0, 220.0, 1))
            c = w + self.down * (top - float(w @ self.down) + 15.0) + R_world[:, 2] * _rand(g, -200.0, 300.0, 1)
            self.T["table"] = _placed(R_world, torch.tensor([700.0, 15.0, 450.0], dtype=torch.float64), c)
        if float(torch.rand(1, generator=g)) < cfg.p_held:
            k = 1 if self.hand_pose[1] is not None else 0
            R, p = self.hand_pose[k]
            palm = p + R[:, 0] * 60.0
            which = ("held_sphere", "held_box", "held_cyl")[int(torch.randint(0, 3, (1,), generator=g))]
            size = _rand(g, 22.0, 45.0, 3)
            if which == "held_cyl":
                size[2] = _rand(g, 60.0, 200.0, 1)
            side = R[:, 1] * (1.0 if float(torch.rand(1, generator=g)) < 0.5 else -1.0)
            Rh = _rotation(torch.randn(3, generator=g, dtype=torch.float64), _rand(g, 0.0, math.pi, 1))
            c = palm + side * (size[:2].mean() + 12.0)
            if which == "held_cyl":
                c = c - Rh @ torch.tensor([0.0, 0.0, float(size[2]) / 2], dtype=torch.float64)
            self.T[which] = _placed(Rh, size, c)
        if float(torch.rand(1, generator=g)) < cfg.p_other_arm:
            a = self._view_point(float(_rand(g, 400.0, 1800.0, 1)))
            b = a + _unit(torch.randn(3, generator=g, dtype=torch.float64)) * 600.0
            self.T["other_arm"] = _limb(a, b, 30.0, 38.0)
        for name in ("clutter_box1", "clutter_box2", "clutter_sphere", "clutter_cyl"):
            if float(torch.rand(1, generator=g)) < cfg.p_clutter:
                size = _rand(g, 20.0, 180.0, 3)
                Rc = _rotation(torch.randn(3, generator=g, dtype=torch.float64), _rand(g, 0.0, math.pi, 1))
                c = self._view_point(float(_rand(g, 250.0, 3000.0, 1)))
                # keep clutter off the hands: push it behind a hand it would cover
                for p in wrists:
                    if (c - p).norm() < float(size.max()) + 120.0:
                        c = c + _unit(c) * (float(size.max()) + 150.0)
                self.T[name] = _placed(Rc, size, c)

    def vertices(self, meshes: _Meshes, hand_verts: List[Optional[torch.Tensor]]) -> torch.Tensor:
        parts, far = [], torch.tensor([0.0, 0.0, -1e4])
        k = 0
        for name, n in meshes.parts:
            if name == "hand":
                v = hand_verts[k]
                parts.append(v.float() if v is not None else far.expand(n, 3))
                k += 1
                continue
            kind = next(s[1] for s in _SLOTS if s[0] == name)
            T = self.T.get(name)
            if T is None:
                parts.append(far.expand(n, 3))
                continue
            tv = torch.from_numpy(meshes.templates[kind][0]).double()
            parts.append((tv @ T[:3, :3].T + T[:3, 3]).float())
        return torch.cat(parts)


def _posed_hands(models, n: int, cfg: ContextConfig, g: torch.Generator, motions) -> tuple:
    """Per hand model: (vertices (n, V, 3), joints (n, 21, 3), scale (n,)) in the hand's
    own rest frame (root at rest), resized and articulated."""
    out = []
    for m, motion in zip(models, motions):
        art = hand_articulations(m, n, g, motion)
        theta = torch.cat([torch.zeros(n, 6), art], 1).to(m.lower.dtype)
        scale = _rand(g, *cfg.scale, n).float()
        fingers = _rand(g, *cfg.finger_factor, n, len(FINGERS)).float()
        with torch.no_grad():
            G = m(theta).G
            verts, _, joints = pose_resized(m, G, bone_scales(m, scale, fingers).to(G.dtype))
        src = joint_sources(m)
        j21 = torch.cat([joints[:, src.bones[:1]],
                         torch.cat([joints[:, src.bones[1:]].reshape(n, 5, 3, 3), verts[:, src.tip_vertices][:, :, None]],
                                   2).reshape(n, 20, 3)], 1)
        out.append((verts.double(), j21.double(), scale))
    return out


def _to_pose(verts: torch.Tensor, j21: torch.Tensor, pose: tuple) -> tuple:
    """Move a hand from its rest frame so that its wrist lies at ``pose``'s position and
    its (finger axis, palm normal) frame is ``pose``'s rotation."""
    wrist = j21[0]
    axis = _unit(j21[9] - wrist)
    normal = _unit(torch.linalg.cross(axis, j21[5] - j21[17]))
    F_rest = torch.stack([axis, normal, torch.linalg.cross(axis, normal)], 1)
    R_t, p = pose
    R = R_t @ F_rest.T
    return (verts - wrist) @ R.T + p, (j21 - wrist) @ R.T + p


def render_context_frames(n: int, seed: int, cfg: ContextConfig = ContextConfig(), motions: Optional[dict] = None,
                          batch_size: int = 8, progress: bool = True, name: str = "context") -> LocaliserFrames:
    """``n`` frames of hands in context (module doc), deterministic in ``seed``.

    ``motions``: per hand model name, (M, D - 6) finger articulations to draw a third of
    the poses from (:func:`hand_articulations`); missing ones use uniform draws.
    """
    from torchhand.model.articulated import load_model

    g = torch.Generator().manual_seed(seed)
    models = [load_model(h) for h in HANDS]
    meshes = _Meshes(models)
    H, W = cfg.height, cfg.width
    depth_o = np.zeros((n, H, W), np.uint16)
    labels_o = np.zeros((n, H, W), np.uint8)
    uv_o = np.full((n, 2, 21, 2), np.nan, np.float32)
    z_o = np.full((n, 2, 21), np.nan, np.float32)
    K_o = np.zeros((n, 3, 3), np.float32)
    kinect = replace(noise_model("kinect"), min_depth_mm=150.0) if cfg.noise == "kinect" else None
    bar = tqdm(total=n, desc=f"render {name}", unit="frame", disable=not progress, leave=False)
    for s in range(0, n, batch_size):
        b = min(batch_size, n - s)
        f = float(_rand(g, *cfg.focal_px, 1))
        cam = Camera.from_intrinsics(f, f, (W - 1) / 2 + float(_rand(g, -15, 15, 1)),
                                     (H - 1) / 2 + float(_rand(g, -10, 10, 1)), W, H)
        K = cam.K.double()
        hands = _posed_hands(models, b, cfg, g, [(motions or {}).get(h) for h in HANDS])
        all_verts, joints = [], np.full((b, 2, 21, 3), np.nan)
        for i in range(b):
            fr = _Frame(cfg, g, K, [(float(h[2][i]),) for h in hands])
            hv = [None, None]
            for k in (0, 1):
                if fr.present[k]:
                    hv[k], j = _to_pose(hands[k][0][i], hands[k][1][i], fr.hand_pose[k])
                    joints[i, k] = j.numpy()
            all_verts.append(fr.vertices(meshes, hv))
        with torch.no_grad():
            res = meshes.renderer(torch.stack(all_verts), cam, normals=False, box=(0, H, 0, W))
        depth = res.depth
        cls = torch.where(res.face_id >= 0, meshes.face_class[res.face_id.clamp_min(0)].long(), torch.zeros_like(res.face_id))
        far = depth.flatten(1).amax(1)
        bg = random_background(torch.where(far > 0, far, torch.full_like(far, 800.0)).clamp_max(3500.0), H, W, g,
                               focal_px=f)
        depth = torch.where(depth > 0, depth, bg)
        if kinect is not None:
            depth = apply_kinect_noise(depth, None, K.float(), kinect, generator=g)
        elif cfg.noise == "stereo":
            depth = apply_stereo_noise(depth, K.float(), StereoNoise(), generator=g)
        lab = torch.where(depth > 0, cls, torch.full_like(cls, IGNORE))
        depth_o[s:s + b] = depth.round().clamp(0, 65535).numpy().astype(np.uint16)
        labels_o[s:s + b] = lab.numpy().astype(np.uint8)
        z = joints[..., 2]
        uv_o[s:s + b, ..., 0] = K[0, 0].item() * joints[..., 0] / z + K[0, 2].item()
        uv_o[s:s + b, ..., 1] = K[1, 1].item() * joints[..., 1] / z + K[1, 2].item()
        z_o[s:s + b] = z
        K_o[s:s + b] = K.numpy()
        bar.update(b)
    bar.close()
    return LocaliserFrames(depth_o, labels_o, uv_o, z_o, K_o, np.array([name] * n))


def concat_localiser_frames(parts: List[LocaliserFrames]) -> LocaliserFrames:
    return LocaliserFrames(*(np.concatenate([getattr(p, f) for p in parts]) for f in LocaliserFrames._fields))


def save_localiser_frames(frames: LocaliserFrames, path) -> None:
    np.savez_compressed(path, **frames._asdict())


def load_localiser_frames(path) -> LocaliserFrames:
    with np.load(path) as d:
        return LocaliserFrames(*(d[f] for f in LocaliserFrames._fields))
