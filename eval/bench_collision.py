"""Collision detection + penalty + gradient in torch against python-fcl detection.

    python eval/bench_collision.py --json out/bench_collision.json [--threads 1] [--repeats 20]

Two posed thesis hands (hand_right and hand_left, 41,302 triangles) from the demo
motion, the left hand pushed into the right one. Times, per evaluation:

* ``torchhand_ms``: :func:`torchhand.geometry.intersections.detect_collisions` between the two
  hands (refitting the hierarchy to the pose), the Eq. 4.13 penalty and its
  gradient with respect to the vertices (``backward``);
* ``torchhand_self_ms``: the same with self-collisions within each hand as well;
* ``fcl_ms``: python-fcl detection of the same pairs on the same meshes, which for
  a new pose means building its BVHs (python-fcl cannot refit) and colliding them;
* ``fcl_collide_ms``: python-fcl's collide call alone on BVHs built beforehand.

``pairs_equal`` says whether both found the same set of intersecting triangle pairs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from _common import machine, median_seconds, set_threads, write_json
from torchhand.geometry.intersections import CollisionMesh, collision_energy, detect_collisions, pair_sets
from torchhand.io.assets import load_demo_motion
from torchhand.model.scene import Scene


def posed_hands(frame: int, push: float, dtype=torch.float32):
    """Vertices (1, V, 3) of the two hands of demo frame ``frame``, the left hand moved
    ``push`` of the way towards the right hand's centroid; and the scene."""
    names, theta = load_demo_motion()
    scene = Scene.from_names(["hand_right", "hand_left"], dtype=dtype)
    th = torch.cat([theta[[frame], :37], theta[[frame], 37:74]], 1).to(dtype)
    with torch.no_grad():
        V = scene(th).vertices
        r, left = scene.vertex_slices["hand_right"], scene.vertex_slices["hand_left"]
        s = scene.slices["hand_left"]
        th[:, s.start : s.start + 3] += push * (V[:, r].mean(1) - V[:, left].mean(1))
        return scene(th).vertices, scene


def fcl_objects(vertices: np.ndarray, faces: np.ndarray, model: np.ndarray):
    import fcl

    objs, groups = [], []
    for k in range(int(model.max()) + 1):
        g = np.nonzero(model == k)[0]
        m = fcl.BVHModel()
        m.beginModel(0, 0)
        m.addSubModel(vertices, faces[g].astype(np.int32))
        m.endModel()
        objs.append(fcl.CollisionObject(m, fcl.Transform()))
        groups.append(g)
    return objs, groups


def fcl_collide(objs, groups):
    import fcl

    req = fcl.CollisionRequest(num_max_contacts=10**7, enable_contact=False)
    res = fcl.CollisionResult()
    fcl.collide(objs[0], objs[1], req, res)
    return {(min(groups[0][c.b1], groups[1][c.b2]), max(groups[0][c.b1], groups[1][c.b2])) for c in res.contacts}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--frame", type=int, default=0, help="demo motion frame")
    ap.add_argument("--push", type=float, default=0.3, help="fraction of the way the left hand is moved into the right")
    args = ap.parse_args(argv)
    set_threads(args.threads)

    V, scene = posed_hands(args.frame, args.push)
    between = CollisionMesh.from_scene(scene, self_collisions=False)
    full = CollisionMesh.from_scene(scene, self_collisions=True)

    def torch_eval(mesh):
        v = V.clone().requires_grad_()
        pairs = detect_collisions(v, mesh)
        collision_energy(v, mesh.faces, pairs).sum().backward()
        return pairs

    pairs = torch_eval(between)
    t_torch = median_seconds(lambda: torch_eval(between), args.repeats)
    t_self = median_seconds(lambda: torch_eval(full), args.repeats)
    n_self = len(torch_eval(full)) - len(pairs)
    result = {"torchhand_ms": 1e3 * t_torch, "torchhand_self_ms": 1e3 * t_self, "pairs": len(pairs),
              "self_pairs": n_self, "triangles": int(scene.faces.shape[0])}
    try:
        import fcl  # noqa: F401
    except ImportError:
        result.update(fcl_ms=None, fcl_collide_ms=None, pairs_equal=None, note="python-fcl is not installed")
    else:
        Vn, F, model = V[0].double().numpy(), scene.faces.numpy(), scene.face_model_id.numpy()
        t_fcl = median_seconds(lambda: fcl_collide(*fcl_objects(Vn, F, model)), max(3, args.repeats // 4))
        objs, groups = fcl_objects(Vn, F, model)
        ref = fcl_collide(objs, groups)
        t_collide = median_seconds(lambda: fcl_collide(objs, groups), args.repeats)
        result.update(fcl_ms=1e3 * t_fcl, fcl_collide_ms=1e3 * t_collide,
                      pairs_equal=pair_sets(pairs, 1)[0] == ref, fcl_pairs=len(ref),
                      speedup_vs_fcl=t_fcl / t_torch)
    result["machine"] = machine()
    write_json(args.json, result)


if __name__ == "__main__":
    main()
