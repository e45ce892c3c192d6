"""The physics simulation of the thesis' grasp term (Ch. 4.2.2.6), on pybullet (Bullet,
as the thesis uses).

A posed scene becomes one convex hull per part: a part is the vertices whose largest
skinning weight is the bone's (the thesis represents each part "defined by the skinning
weights" as a convex hull). The contact candidates are the parts of the highest zone
of the hand's ZONES file (the phalanges; the thesis' Fig. 4.10 excludes the palm and
the arm, which the file ranks lower). The hands are static; a rigid object (one bone) is a dynamic body of 1 kg
(restitution 0.5, friction equal to the hands'); gravity pulls along the world's +y
(the image's down for a level camera with the world in camera 0, as the thesis
sequences are; ``gravity`` sets another direction).

:meth:`GraspSimulation.displacement` runs the thesis' test: 35 steps of 0.1 s (each in
``substeps`` sub-steps: at 0.1 s a falling box tunnels through thin parts otherwise) and
returns how far the object's centroid moved. :meth:`GraspSimulation.best_support` tries
every combination of two to four candidate finger parts (phalanges within 10 mm of the
object), each part moved rigidly onto the object's nearest surface point, and returns
the most stable one.

Choices the thesis leaves open, made here: the static scene (the thesis models a table)
is absent, since torchhand's scenes have none, so an object held in the air is unstable
until fingers support it; at most ``max_candidates`` nearest candidates are
combined (the thesis combines all), bounding a frame's simulations at 50.
"""

from __future__ import annotations

import itertools
from typing import Dict, List, NamedTuple, Sequence, Tuple

import numpy as np

__all__ = ["GraspSimulation", "Support", "part_vertices", "contact_bones", "require_pybullet"]

_M = 1e-3  # pybullet works in metres; torchhand in mm


def require_pybullet():
    try:
        import pybullet
    except ImportError:
        raise ImportError("the physics term needs pybullet: pip install 'torchhand[physics]'") from None
    return pybullet


def part_vertices(model) -> List[np.ndarray]:
    """Per bone, the ids of the vertices that form its part: those whose largest
    skinning weight is the bone's."""
    idx = model.skin_index.cpu().numpy()
    w = model.skin_weight.cpu().numpy()
    dominant = idx[np.arange(len(idx)), w.argmax(1)]
    return [np.nonzero(dominant == j)[0] for j in range(model.num_bones)]


def contact_bones(model) -> List[int]:
    """The bones that may support an object: those of the highest zone in the model's
    ZONES file (the hands': the phalanges at 1.0, the metacarpals at 0.7, the arm at 0.1),
    never the root. A model without ZONES has none (a ValueError says so)."""
    zones = model.assets.zones or {}
    if not zones:
        raise ValueError(f"model {model.name!r} has no ZONES (contact zones): the physics term cannot choose "
                         "its contact parts")
    top = max(zones.values())
    out = []
    for j, name in enumerate(model.bone_names):
        value = next((t for key, t in zones.items() if key in name), None)
        if j > 0 and value is not None and value >= top:
            out.append(j)
    return out


class Support(NamedTuple):
    """The outcome for one object: stable (bool), displacement (mm, of the object as
    posed), parts ([(model index, bone index)] of the chosen combination, empty when
    stable or none helps), supported (mm, the displacement with the combination)."""

    stable: bool
    displacement: float
    parts: List[Tuple[int, int]]
    supported: float


class GraspSimulation:
    """Bullet simulation of one posed frame of a scene (hands static, one rigid object
    dynamic at a time).

    Args:
        scene: the :class:`~torchhand.model.scene.Scene`.
        friction: of the hands and the objects (the thesis finds the value uncritical).
        steps, dt, substeps: the simulation (thesis: 35 steps of 0.1 s).
        stable_mm: an object moving less than this is stable (thesis: 3 mm).
        contact_mm: finger parts nearer than this are contact candidates (thesis: 10 mm).
        max_candidates: the nearest candidates combined.
        gravity: (3,) mm/s^2 in the world frame.
    """

    def __init__(self, scene, friction: float = 1.2, steps: int = 35, dt: float = 0.1, substeps: int = 10,
                 stable_mm: float = 3.0, contact_mm: float = 10.0, max_candidates: int = 6,
                 gravity: Sequence[float] = (0.0, 9810.0, 0.0)):
        self.pb = require_pybullet()
        self.scene = scene
        self.friction, self.steps, self.dt, self.substeps = float(friction), int(steps), float(dt), int(substeps)
        self.stable_mm, self.contact_mm, self.max_candidates = float(stable_mm), float(contact_mm), int(max_candidates)
        self.gravity = tuple(float(g) * _M for g in gravity)
        self.parts = [part_vertices(m) for m in scene.models]
        self.hands = [k for k, m in enumerate(scene.models) if m.kind == "hand"]
        self.objects = [k for k, m in enumerate(scene.models) if m.kind != "hand" and m.num_bones == 1]
        # candidate contact parts: the hands' highest ZONES (the phalanges)
        self.fingers = [(k, j) for k in self.hands for j in contact_bones(scene.models[k])
                        if len(self.parts[k][j]) >= 4]

    # ---------------------------------------------------------------- bodies
    def _world(self, vertices: Dict[int, np.ndarray]):
        pb = self.pb
        client = pb.connect(pb.DIRECT)
        pb.setGravity(*self.gravity, physicsClientId=client)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSubSteps=self.substeps, physicsClientId=client)
        bodies = {}
        for k in self.hands:
            for j, ids in enumerate(self.parts[k]):
                if len(ids) >= 4:
                    bodies[(k, j)] = self._body(client, vertices[k][ids], 0.0, 0.0)
        return client, bodies

    def _body(self, client, points: np.ndarray, mass: float, restitution: float) -> int:
        pb = self.pb
        centre = points.mean(0)
        shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=((points - centre) * _M).tolist(),
                                        physicsClientId=client)
        body = pb.createMultiBody(baseMass=mass, baseCollisionShapeIndex=shape,
                                  basePosition=(centre * _M).tolist(), physicsClientId=client)
        pb.changeDynamics(body, -1, lateralFriction=self.friction, restitution=restitution, physicsClientId=client)
        return body

    def _simulate(self, client, body) -> float:
        pb = self.pb
        start = np.array(pb.getBasePositionAndOrientation(body, physicsClientId=client)[0])
        pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=client)
        for _ in range(self.steps):
            pb.stepSimulation(physicsClientId=client)
        end = np.array(pb.getBasePositionAndOrientation(body, physicsClientId=client)[0])
        return float(np.linalg.norm(end - start) / _M)

    # ---------------------------------------------------------------- tests
    def best_support(self, vertices: Dict[int, np.ndarray]) -> Dict[int, Support]:
        """The thesis' stability test and search for every rigid object of one frame.

        vertices: {model index: (V_k, 3) posed vertices, mm}. Returns {object index:
        :class:`Support`}.
        """
        pb = self.pb
        out = {}
        client, parts = self._world(vertices)
        try:
            for o in self.objects:
                obj = self._body(client, vertices[o], 1.0, 0.5)
                start = pb.getBasePositionAndOrientation(obj, physicsClientId=client)
                moved = self._simulate(client, obj)
                if moved < self.stable_mm:
                    out[o] = Support(True, moved, [], moved)
                    pb.removeBody(obj, physicsClientId=client)
                    continue
                pb.resetBasePositionAndOrientation(obj, *start, physicsClientId=client)
                near = []
                for key in self.fingers:
                    pts = pb.getClosestPoints(parts[key], obj, self.contact_mm * _M, physicsClientId=client)
                    if pts:
                        best = min(pts, key=lambda p: p[8])
                        near.append((best[8] / _M, key, (np.array(best[6]) - np.array(best[5])) / _M))
                near = sorted(near, key=lambda x: x[0])[: self.max_candidates]
                best_combo, best_moved = [], moved
                for n in range(2, min(4, len(near)) + 1):
                    for combo in itertools.combinations(near, n):
                        homes = {}
                        for _, key, shift in combo:  # each part rigidly onto the object's surface
                            pos, orn = pb.getBasePositionAndOrientation(parts[key], physicsClientId=client)
                            homes[key] = (pos, orn)
                            pb.resetBasePositionAndOrientation(parts[key], (np.array(pos) + shift * _M).tolist(), orn,
                                                               physicsClientId=client)
                        pb.resetBasePositionAndOrientation(obj, *start, physicsClientId=client)
                        d = self._simulate(client, obj)
                        for key, (pos, orn) in homes.items():
                            pb.resetBasePositionAndOrientation(parts[key], pos, orn, physicsClientId=client)
                        if d < best_moved:
                            best_combo, best_moved = [key for _, key, _ in combo], d
                out[o] = Support(False, moved, best_combo, best_moved)
                pb.removeBody(obj, physicsClientId=client)
        finally:
            pb.disconnect(physicsClientId=client)
        return out

    def displacement(self, vertices: Dict[int, np.ndarray]) -> Dict[int, float]:
        """mm each rigid object's centroid moves in the simulation of the frame as posed
        (the thesis' plausibility measure: 9.26 mm for LO+SC, 9.05 mm for LO+SCP)."""
        pb = self.pb
        client, _ = self._world(vertices)
        try:
            out = {}
            for o in self.objects:
                obj = self._body(client, vertices[o], 1.0, 0.5)
                out[o] = self._simulate(client, obj)
                pb.removeBody(obj, physicsClientId=client)
            return out
        finally:
            pb.disconnect(physicsClientId=client)

